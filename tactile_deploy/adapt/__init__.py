"""On-device self-supervised adaptation of a sensor plugin's model (docs/adaptation.md).

``tactile-deploy adapt`` reads unlabelled frames of a sensor, turns them into depth maps with the
plugin's imaging pipeline, runs the exported adaptation step (a torch program: autograd and Adam
here) and writes the adapted ONNX model into the plugin as a new version when the held-out
label-free error improved. torch and onnx are needed only here (``pip install
'tactile-deploy[adapt]'``); importing this package does not import them.
"""
