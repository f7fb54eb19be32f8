"""Console scripts of assist_perception: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

encoder_node = quiet_main('assist_perception.encoder_node')
make_dataset = quiet_main('assist_perception.dataset', TOOL_INTERRUPTED)
train_cmvae = quiet_main('assist_perception.train', TOOL_INTERRUPTED)
evaluate_cmvae = quiet_main('assist_perception.evaluate', TOOL_INTERRUPTED)
