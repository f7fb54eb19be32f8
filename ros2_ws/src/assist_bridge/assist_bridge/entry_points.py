"""Console scripts of assist_bridge: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import quiet_main

mavlink_bridge_node = quiet_main('assist_bridge.mavlink_bridge_node')
teleop_keyboard = quiet_main('assist_bridge.teleop_keyboard')
landing_runner = quiet_main('assist_bridge.landing_runner')
image_relay = quiet_main('assist_bridge.image_relay')
image_decoder = quiet_main('assist_bridge.image_decoder')
