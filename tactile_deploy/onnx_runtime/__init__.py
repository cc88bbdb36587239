"""The one owner of onnxruntime: sessions with explicit providers (:mod:`.session`) and the mesh
model contract checked at load (:mod:`.contract`).

Every ONNX model the product runs (the mesh model, the learned read-out, the adapted models) gets
its ``onnxruntime.InferenceSession`` from :func:`.session.make_session`.
"""
