"""Console scripts of assist_station: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

pilot_station = quiet_main('assist_station.pilot_station')
simulate_study = quiet_main('assist_station.simulate_study', TOOL_INTERRUPTED)
analyze_study = quiet_main('assist_station.analyze_study', TOOL_INTERRUPTED)
