"""ONNX Runtime inference of the CM-VAE's encoder + pad-XYZ head (CPU), exported from the one CMVAE.

Why: at batch 1 on a 64x64 frame torch's per-operator dispatch dominates the CM-VAE's cost. ONNX
Runtime runs the same graph (batch-norms folded, convolutions in its blocked layout) in ~0.13 ms
instead of ~0.7 ms back to back, and ~0.6 ms instead of ~1.7-2.3 ms when each frame follows a
50 ms pause as at 20 Hz (cold caches; bench `perception` row "CM-VAE mu + xyz, torch / onnxruntime").
There is no second model file and no second model definition: the session is exported in memory
from the loaded `CMVAE` at start-up (~0.2 s), so it always has the weights torch has. mu and the
pad XYZ agree with torch to ~1e-6 (test_perception_onnx_backend.py).
"""
from __future__ import annotations

import importlib.util
import io
import logging
import warnings

import numpy as np
import torch
from torch import nn

from .model import CMVAE, preprocess_tensor

_LOG = logging.getLogger(__name__)
BACKENDS = ('auto', 'torch', 'onnxruntime')


class _MuXyz(nn.Module):
    """The per-frame path as one graph: raw 64x64 frames -> (mu, pad XYZ in metres, valid-depth fraction).

    The input scaling is `preprocess_tensor` itself, so the graph and training cannot disagree; doing
    it in the graph saves the dozen small numpy calls that cost ~0.5 ms with cold caches at 20 Hz."""

    def __init__(self, model: CMVAE):
        super().__init__()
        self.model = model

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """rgb (N,64,64,3) uint8, depth (N,64,64) float32 m -> mu (N,L), xyz (N,3), valid (N,)."""
        mu, _ = self.model.encode(preprocess_tensor(rgb, depth, self.model.cfg))
        valid = (torch.isfinite(depth) & (depth > 0)).to(torch.float32).mean(dim=(1, 2))
        return mu, self.model.decode_xyz(mu), valid


def resolve_backend(backend: str, device: torch.device) -> str:
    """'auto' -> onnxruntime on CPU when installed, else torch; a bad name or an impossible choice -> ValueError."""
    if backend not in BACKENDS:
        raise ValueError(f'unknown inference backend {backend!r} (one of {", ".join(BACKENDS)})')
    have_ort = importlib.util.find_spec('onnxruntime') is not None and importlib.util.find_spec('onnx') is not None
    if backend == 'auto':
        if device.type == 'cpu' and not have_ort:
            _LOG.warning('onnxruntime/onnx not installed: the CM-VAE runs on torch (about 3x the CPU per frame)')
        return 'onnxruntime' if device.type == 'cpu' and have_ort else 'torch'
    if backend == 'onnxruntime' and device.type != 'cpu':
        raise ValueError(f'backend onnxruntime runs on the CPU only (device {device}); use backend torch')
    if backend == 'onnxruntime' and not have_ort:
        raise ValueError('backend onnxruntime: the onnxruntime and onnx packages are not installed')
    return backend


def export_mu_xyz(model: CMVAE) -> bytes:
    """ONNX bytes of input scaling + encoder mean + pad-XYZ head, batch dynamic (model left unchanged)."""
    s = model.cfg.image_size
    was_training = model.training
    model.eval()
    buf = io.BytesIO()
    try:
        with warnings.catch_warnings():
            # torch 2.13's TorchScript-based exporter warns that it is legacy; it needs no onnxscript and
            # exports this plain conv net exactly (checked against torch in the tests)
            warnings.filterwarnings('ignore', category=DeprecationWarning)
            warnings.filterwarnings('ignore', message='.*legacy TorchScript-based ONNX export.*')
            torch.onnx.export(_MuXyz(model), (torch.zeros(1, s, s, 3, dtype=torch.uint8), torch.ones(1, s, s)),
                              buf, input_names=['rgb', 'depth'], output_names=['mu', 'xyz', 'valid'],
                              dynamic_axes={'rgb': {0: 'n'}, 'depth': {0: 'n'}}, dynamo=False)
    finally:
        model.train(was_training)
    return buf.getvalue()


class OnnxMuXyz:
    """An ONNX Runtime session computing (mu, xyz, valid-depth fraction) from raw 64x64 RGB-D frames."""

    def __init__(self, model: CMVAE, threads: int = 1):
        import onnxruntime as ort   # imported here: only this backend needs it

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(0, int(threads))    # 0 = ORT's default (one per core)
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # idle intra-op threads sleep instead of spinning: the per-frame path must not burn a core
        opts.add_session_config_entry('session.intra_op.allow_spinning', '0')
        opts.log_severity_level = 3       # errors only: ORT's info lines are not for our users
        model_cpu = model if next(model.parameters()).device.type == 'cpu' else model.cpu()
        self.session = ort.InferenceSession(export_mu_xyz(model_cpu), opts, providers=['CPUExecutionProvider'])
        _LOG.debug('onnxruntime %s session for the CM-VAE (%d intra-op threads)', ort.__version__, threads)

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rgb (N,64,64,3) uint8, depth (N,64,64) metres -> mu (N,L), xyz (N,3), valid (N,), float32."""
        return tuple(self.session.run(None, {'rgb': np.ascontiguousarray(rgb, dtype=np.uint8),
                                             'depth': np.ascontiguousarray(depth, dtype=np.float32)}))
