"""Console scripts of assist_bags: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

bag_record = quiet_main('assist_bags.record_node')
bag_play = quiet_main('assist_bags.play_node')
replay_assist = quiet_main('assist_bags.replay', TOOL_INTERRUPTED)
plot_flight = quiet_main('assist_bags.plot', TOOL_INTERRUPTED)
