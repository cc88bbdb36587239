"""The error of an ONNX model that cannot be used."""

from __future__ import annotations


class ModelContractError(ValueError):
    """An ONNX model does not load or does not follow the contract (names, shapes, metadata,
    mesh hash); the message names the model, what was expected and what was found."""
