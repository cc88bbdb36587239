"""Sim-to-real adaptation of the predictor: a differentiable depth renderer of the predicted
mesh, the self-supervised adaptation step (paper, "Self-Supervised Adaptation"), its export as a
torch program the runtime runs without this package, and the evaluation on target domains."""
