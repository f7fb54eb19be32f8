"""ONNX Runtime inference of the CM-VAE's encoder + pad-XYZ head (CPU), exported from the one CMVAE.

Why: at batch 1 on a 64x64 frame torch's per-operator dispatch dominates the CM-VAE's cost. ONNX
Runtime runs the same graph (batch-norms folded, convolutions in its blocked layout) in ~0.13 ms
instead of ~0.7 ms back to back, and ~0.6 ms instead of ~1.7-2.3 ms when each frame follows a
50 ms pause as at 20 Hz (cold caches; bench `perception` row "CM-VAE mu + xyz, torch / onnxruntime").
There is no second model file to ship and no second model definition: the session is exported from
the loaded `CMVAE` at start-up, so it always has the weights torch has. mu and the pad XYZ agree with
torch to ~1e-6 (test_perception_onnx_backend.py).

An export costs ~2 s of start-up (importing `onnx` and tracing), so the exported bytes are kept in a
cache keyed by a hash of the weights, the model config, torch's version and the export settings
(`$ASSIST_CACHE_DIR/onnx`, default `$XDG_CACHE_HOME/assist/onnx` or `~/.cache/assist/onnx`; set
`ASSIST_CACHE_DIR=off` to export every time). A cached session must reproduce torch's mu and pad XYZ on
a probe frame before it is used; a cache file that does not load or does not agree is exported again
and replaced; a cache that cannot be written (read-only or full disk) is only logged. The newest
`CACHE_KEEP` files are kept.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import logging
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from assist_common.cache import cache_dir as user_cache_dir, store, touch
from assist_common.onnx_session import cpu_session

from .model import CMVAE, preprocess_tensor

_LOG = logging.getLogger(__name__)
BACKENDS = ('auto', 'torch', 'onnxruntime')
CACHE_KEEP = 16                 # exported models kept in the cache, newest first (~2 MB each)
EXPORT_VERSION = 1              # bump when export_mu_xyz changes what it exports


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


@contextlib.contextmanager
def _eval_mode(model: CMVAE):
    """`model` in eval mode inside the block, back in the mode it had after it."""
    was_training = model.training
    model.eval()
    try:
        yield model
    finally:
        model.train(was_training)


def export_mu_xyz(model: CMVAE) -> bytes:
    """ONNX bytes of input scaling + encoder mean + pad-XYZ head, batch dynamic (model left unchanged)."""
    s = model.cfg.image_size
    buf = io.BytesIO()
    with _eval_mode(model):
        with warnings.catch_warnings():
            # torch 2.13's TorchScript-based exporter warns that it is legacy; it needs no onnxscript and
            # exports this plain conv net exactly (checked against torch in the tests)
            warnings.filterwarnings('ignore', category=DeprecationWarning)
            warnings.filterwarnings('ignore', message='.*legacy TorchScript-based ONNX export.*')
            torch.onnx.export(_MuXyz(model), (torch.zeros(1, s, s, 3, dtype=torch.uint8), torch.ones(1, s, s)),
                              buf, input_names=['rgb', 'depth'], output_names=['mu', 'xyz', 'valid'],
                              dynamic_axes={'rgb': {0: 'n'}, 'depth': {0: 'n'}}, dynamo=False)
    return buf.getvalue()


def cache_dir() -> Path | None:
    """Where exported encoders are cached (None when ASSIST_CACHE_DIR is 'off')."""
    return user_cache_dir('onnx')


def export_key(model: CMVAE) -> str:
    """A hash of everything the export depends on: weights and buffers, config, torch version, export version."""
    h = hashlib.sha256(f'{EXPORT_VERSION}|{torch.__version__}|{model.cfg!r}'.encode())
    for name, tensor in model.state_dict().items():
        t = tensor.detach().cpu().contiguous()
        h.update(f'{name}|{t.dtype}|{tuple(t.shape)}'.encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:32]


def _check_against_torch(session, model: CMVAE, tol: float = 1e-3) -> None:
    """ValueError unless `session` gives torch's mu and pad XYZ on a fixed probe frame (to `tol`)."""
    s = model.cfg.image_size
    gen = torch.Generator().manual_seed(0)
    rgb = torch.randint(0, 256, (1, s, s, 3), dtype=torch.uint8, generator=gen)
    depth = 0.5 + 9.5 * torch.rand(1, s, s, generator=gen)
    with _eval_mode(model), torch.no_grad():
        mu_t, xyz_t, _ = _MuXyz(model)(rgb, depth)
    mu_o, xyz_o, _ = session.run(None, {'rgb': rgb.numpy(), 'depth': depth.numpy()})
    # equal_nan: a model whose output overflows gives inf/NaN in both (encoder_core reports such frames as bad)
    if not all(np.allclose(o, t.numpy(), rtol=0.0, atol=tol, equal_nan=True)
               for o, t in ((mu_o, mu_t), (xyz_o, xyz_t))):
        raise ValueError(f"its mu or pad XYZ differs from the model's by more than {tol:g} on a probe frame")


class OnnxMuXyz:
    """An ONNX Runtime session computing (mu, xyz, valid-depth fraction) from raw 64x64 RGB-D frames."""

    def __init__(self, model: CMVAE, threads: int = 1):
        self.threads = threads
        model_cpu = model if next(model.parameters()).device.type == 'cpu' else model.cpu()
        self.session = self._session(model_cpu)
        _LOG.debug('onnxruntime session for the CM-VAE (%d intra-op threads)', threads)

    def _session(self, model: CMVAE):
        """A session from the cached export of `model` when there is a loadable one, else from a new export."""
        folder = cache_dir()
        path = folder / f'{export_key(model)}.onnx' if folder is not None else None
        if path is not None and path.is_file():
            try:
                session = cpu_session(path, self.threads)
                _check_against_torch(session, model)
            except Exception as exc:  # noqa: BLE001 - ORT raises its own types for a corrupt file
                _LOG.warning('cached CM-VAE export %s is not usable (%s): exporting it again', path, exc)
            else:
                touch(path)                       # recently used: kept by the pruning
                return session
        data = export_mu_xyz(model)
        session = cpu_session(data, self.threads)
        if path is not None:
            store(path, data, CACHE_KEEP, 'the exported CM-VAE encoder')
        return session

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rgb (N,64,64,3) uint8, depth (N,64,64) metres -> mu (N,L), xyz (N,3), valid (N,), float32."""
        return tuple(self.session.run(None, {'rgb': np.ascontiguousarray(rgb, dtype=np.uint8),
                                             'depth': np.ascontiguousarray(depth, dtype=np.float32)}))
