"""Torch simulation for training data at scale: the batched contact simulator and the batched
depth camera (need the ``train`` extra; the runtime's numpy simulator is
:mod:`tactile_deploy.simulation`)."""
