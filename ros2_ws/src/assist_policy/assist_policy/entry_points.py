"""Console scripts of assist_policy: each imports its module only when run (a Ctrl-C during start-up exits
without a traceback; see assist_common.console)."""
from assist_common.console import TOOL_INTERRUPTED, quiet_main

policy_node = quiet_main('assist_policy.policy_node')
train_td3 = quiet_main('assist_policy.train', TOOL_INTERRUPTED)
evaluate = quiet_main('assist_policy.evaluate', TOOL_INTERRUPTED)
evaluate_graph = quiet_main('assist_policy.graph_eval', TOOL_INTERRUPTED)
compare_landings = quiet_main('assist_policy.compare', TOOL_INTERRUPTED)
bag_record = quiet_main('assist_policy.bags.record_node')
bag_play = quiet_main('assist_policy.bags.play_node')
replay_assist = quiet_main('assist_policy.bags.replay', TOOL_INTERRUPTED)
plot_flight = quiet_main('assist_policy.bags.plot', TOOL_INTERRUPTED)
