"""The gray-box model: white-box law corrected by a small network, one ONNX graph, run by onnxruntime.

Loading needs only numpy and onnxruntime; training (``cmcan.model.train``) needs ``cmcan[train]``.
"""

from cmcan.model.metadata import ModelError, ModelMeta
from cmcan.model.runtime import GrayBoxModel, default_model_path, load_model

__all__ = ["GrayBoxModel", "ModelError", "ModelMeta", "default_model_path", "load_model"]
