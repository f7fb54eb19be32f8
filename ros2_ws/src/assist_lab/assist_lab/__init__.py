"""The research lab: the simulated landing env, TD3 and CM-VAE training, evaluation against simulated pilots (in
process and through the node graph) and landing comparison. Never installed on a vehicle: it needs the simulator,
gymnasium, matplotlib and (optionally) Ray."""
