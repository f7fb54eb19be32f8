"""Console scripts of assist_lab: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

train_td3 = quiet_main('assist_lab.train', TOOL_INTERRUPTED)
evaluate = quiet_main('assist_lab.evaluate', TOOL_INTERRUPTED)
evaluate_graph = quiet_main('assist_lab.graph_eval', TOOL_INTERRUPTED)
compare_landings = quiet_main('assist_lab.compare', TOOL_INTERRUPTED)
make_dataset = quiet_main('assist_lab.cmvae_dataset', TOOL_INTERRUPTED)
train_cmvae = quiet_main('assist_lab.cmvae_train', TOOL_INTERRUPTED)
evaluate_cmvae = quiet_main('assist_lab.cmvae_evaluate', TOOL_INTERRUPTED)
