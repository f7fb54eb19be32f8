"""The assistant a vehicle runs: observation, the learned actor, the non-learned stages and policy_node."""
