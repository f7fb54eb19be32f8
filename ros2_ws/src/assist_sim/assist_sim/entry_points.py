"""Console scripts of assist_sim: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

sim_node = quiet_main('assist_sim.sim_node')
sim_pilot_node = quiet_main('assist_sim.sim_pilot_node')
sitl_identify = quiet_main('assist_sim.sitl_identify', TOOL_INTERRUPTED)
fit_guided = quiet_main('assist_sim.guided_fit', TOOL_INTERRUPTED)
