"""Learned read-out of a sensor design: a family of virtual units, their ball presses, a small
convolutional network from colour to depth, and its ONNX export
(:mod:`tactile_deploy.imaging.learned_readout` runs it).

    python -m tactile_deploy.training.shading_net --design gelslim1 --out exported/gelslim_readout.onnx --overwrite
"""
