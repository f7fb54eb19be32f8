"""Console scripts of assist_perception: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import quiet_main

encoder_node = quiet_main('assist_perception.encoder_node')
