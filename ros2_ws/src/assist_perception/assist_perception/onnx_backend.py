"""ONNX Runtime inference of the CM-VAE (CPU): the per-frame encoder + pad-XYZ head and the depth decoder, exported
from the one CMVAE.

Why: at batch 1 on a 64x64 frame torch's per-operator dispatch dominates the CM-VAE's cost. ONNX
Runtime runs the same graph (batch-norms folded, convolutions in its blocked layout) in ~0.13 ms
instead of ~0.7 ms back to back, and ~0.6 ms instead of ~1.7-2.3 ms when each frame follows a
50 ms pause as at 20 Hz (cold caches; bench `perception` row "CM-VAE mu + xyz, torch / onnxruntime").
There is no second model file to ship and no second model definition: the sessions are exported from
the weights file's `CMVAE`, so they always have the weights torch has. mu, the pad XYZ and the denoised
depth agree with torch to ~1e-6 (test_perception_onnx_backend.py).

Importing torch and exporting cost seconds at every start, so the exports are kept in the user cache
(`assist_common.cache`, folder `onnx`: `$ASSIST_CACHE_DIR/onnx`, default `~/.cache/assist/onnx`;
`ASSIST_CACHE_DIR=off` exports every time), keyed by a hash of the weights file's bytes, torch's version
and the export version, beside the model's sizes and a probe frame's outputs as torch computed them at
export time. A start whose export is cached imports neither torch nor onnx; a cached entry is used only
when its sessions reproduce the probe (to PROBE_TOL), and an entry that does not load or agree is
exported again and replaced; a cache that cannot be written (read-only or full disk) is only logged.
The newest `CACHE_KEEP` entries are kept.
"""
from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import logging
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from assist_common.cache import cache_dir as user_cache_dir, file_key, store_entry, touch
from assist_common.console import package_version
from assist_common.onnx_session import cpu_session

if TYPE_CHECKING:
    from .model import CMVAE

_LOG = logging.getLogger(__name__)
BACKENDS = ('auto', 'torch', 'onnxruntime')
CACHE_KEEP = 16                 # exported models kept in the cache, newest first (~2 MB each)
EXPORT_VERSION = 2              # bump when the exports change what they compute
PROBE_TOL = 1e-3                # mu and pad XYZ (network units, metres) and depth (metres) against torch's


class ExportDisagrees(Exception):
    """An ONNX export whose outputs differ from torch's on the probe frame."""


def resolve_backend(backend: str, device_type: str) -> str:
    """'auto' -> onnxruntime on CPU when installed, else torch; a bad name or an impossible choice -> ValueError."""
    if backend not in BACKENDS:
        raise ValueError(f'unknown inference backend {backend!r} (one of {", ".join(BACKENDS)})')
    have_ort = importlib.util.find_spec('onnxruntime') is not None and importlib.util.find_spec('onnx') is not None
    if backend == 'auto':
        if device_type == 'cpu' and not have_ort:
            _LOG.warning('onnxruntime/onnx not installed: the CM-VAE runs on torch (about 3x the CPU per frame)')
        return 'onnxruntime' if device_type == 'cpu' and have_ort else 'torch'
    if backend == 'onnxruntime' and device_type != 'cpu':
        raise ValueError(f'backend onnxruntime runs on the CPU only (device {device_type}); use backend torch')
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


def _graphs(model: CMVAE) -> tuple[Any, Any]:
    """(mu/xyz graph, depth graph) as torch modules around `model`."""
    import torch
    from torch import nn

    from .model import preprocess_tensor

    class MuXyz(nn.Module):
        """The per-frame path as one graph: raw 64x64 frames -> (mu, pad XYZ in metres, valid-depth fraction).

        The input scaling is `preprocess_tensor` itself, so the graph and training cannot disagree; doing
        it in the graph saves the dozen small numpy calls that cost ~0.5 ms with cold caches at 20 Hz."""

        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, rgb: torch.Tensor, depth: torch.Tensor):
            mu, _ = self.model.encode(preprocess_tensor(rgb, depth, self.model.cfg))
            valid = (torch.isfinite(depth) & (depth > 0)).to(torch.float32).mean(dim=(1, 2))
            return mu, self.model.decode_xyz(mu), valid

    class Depth(nn.Module):
        """The depth decoder: mu (N, L) -> denoised depth (N, 64, 64) in metres."""

        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, mu: torch.Tensor) -> torch.Tensor:
            return self.model.decode_depth(mu)
    return MuXyz(), Depth()


def _export(module: Any, args: tuple, inputs: list[str], outputs: list[str]) -> bytes:
    """ONNX bytes of `module` on `args`, the first axis of every input and output dynamic."""
    import torch
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # torch's TorchScript-based exporter warns that it is legacy; it needs no onnxscript and exports this plain
        # conv net exactly (checked against torch on the probe frame)
        warnings.filterwarnings('ignore', category=DeprecationWarning)
        warnings.filterwarnings('ignore', message='.*legacy TorchScript-based ONNX export.*')
        torch.onnx.export(module, args, buf, input_names=inputs, output_names=outputs,
                          dynamic_axes={name: {0: 'n'} for name in inputs + outputs}, dynamo=False)
    return buf.getvalue()


def export_mu_xyz(model: CMVAE) -> bytes:
    """ONNX bytes of input scaling + encoder mean + pad-XYZ head, batch dynamic (model left unchanged)."""
    import torch
    s = model.cfg.image_size
    with _eval_mode(model):
        return _export(_graphs(model)[0], (torch.zeros(1, s, s, 3, dtype=torch.uint8), torch.ones(1, s, s)),
                       ['rgb', 'depth'], ['mu', 'xyz', 'valid'])


def export_depth(model: CMVAE) -> bytes:
    """ONNX bytes of the depth decoder, mu -> metres, batch dynamic (model left unchanged)."""
    import torch
    with _eval_mode(model):
        return _export(_graphs(model)[1], (torch.zeros(1, model.cfg.latent_dim),), ['mu'], ['depth'])


def cache_dir() -> Path | None:
    """Where exported encoders are cached (None when ASSIST_CACHE_DIR is 'off')."""
    return user_cache_dir('onnx')


def export_key(path: str | Path) -> str:
    """A hash of what the exports depend on: the weights file's bytes, torch's version, the export version."""
    return file_key(path, str(EXPORT_VERSION), package_version('torch'))


def probe_frame(size: int) -> tuple[np.ndarray, np.ndarray]:
    """A fixed RGB-D frame (batch of one) to compare the exports with torch on."""
    rng = np.random.default_rng(0)
    return (rng.integers(0, 256, (1, size, size, 3), dtype=np.uint8),
            rng.uniform(0.5, 10.0, (1, size, size)).astype(np.float32))


def torch_outputs(model: CMVAE, rgb: np.ndarray, depth: np.ndarray) -> dict[str, np.ndarray]:
    """mu, pad XYZ and denoised depth of frames as torch computes them (the reference for the exports)."""
    import torch
    mu_xyz, dec = _graphs(model)
    with _eval_mode(model), torch.no_grad():
        mu, xyz, _ = mu_xyz(torch.from_numpy(rgb), torch.from_numpy(depth))
        return {'mu': mu.numpy(), 'xyz': xyz.numpy(), 'depth': dec(mu).numpy()}


class OnnxCMVAE:
    """ONNX Runtime sessions of one CM-VAE weights file: (mu, xyz, valid-depth fraction) from raw 64x64 RGB-D frames,
    and the denoised depth of a mu; from the cached export when there is a usable one (no torch), else exported from
    the model `load_model()` returns."""

    def __init__(self, path: str | Path, load_model: Callable[[], CMVAE], threads: int = 1):
        self.path, self.threads = Path(path), threads
        self.latent_dim, self.image_size = 0, 0
        self._load(load_model)
        _LOG.debug('onnxruntime sessions for the CM-VAE %s (%d intra-op threads)', self.path, threads)

    def _load(self, load_model: Callable[[], CMVAE]) -> None:
        folder = cache_dir()
        key = export_key(self.path)
        probe = folder / f'{key}.json' if folder is not None else None
        if probe is not None and probe.is_file():
            try:
                entry = json.loads(probe.read_text())
                self.latent_dim, self.image_size = int(entry['latent_dim']), int(entry['image_size'])
                self.mu_xyz = cpu_session(folder / f'{key}.onnx', self.threads)
                self.depth = cpu_session(folder / f'{key}.depth.onnx', self.threads)
                self._check({k: np.asarray(entry[k], np.float32) for k in ('mu', 'xyz', 'depth')})
            except Exception as exc:  # noqa: BLE001 - ORT, json and the checks raise many types for a bad entry
                _LOG.warning('cached CM-VAE export %s is not usable (%s): exporting it again', probe, exc)
            else:
                for f in folder.glob(f'{key}.*'):
                    touch(f)                  # recently used: kept by the pruning
                return
        model = load_model()
        if next(model.parameters()).device.type != 'cpu':
            model = model.cpu()
        self.latent_dim, self.image_size = int(model.cfg.latent_dim), int(model.cfg.image_size)
        data, depth = export_mu_xyz(model), export_depth(model)
        self.mu_xyz, self.depth = cpu_session(data, self.threads), cpu_session(depth, self.threads)
        ref = torch_outputs(model, *probe_frame(self.image_size))
        self._check(ref)
        if folder is not None:
            entry = {'latent_dim': self.latent_dim, 'image_size': self.image_size, 'source': str(self.path),
                     **{k: v.tolist() for k, v in ref.items()}}
            # the probe last: an entry without it is never read as a hit
            store_entry(folder, key, {'.onnx': data, '.depth.onnx': depth, '.json': json.dumps(entry).encode()},
                        CACHE_KEEP, 'the exported CM-VAE')

    def _check(self, ref: dict[str, np.ndarray]) -> None:
        """ExportDisagrees unless the sessions give `ref` (torch's outputs) on the probe frame, to PROBE_TOL."""
        mu, xyz, _ = self(*probe_frame(self.image_size))
        got = {'mu': mu, 'xyz': xyz, 'depth': self.decode_depth(mu)}
        for name, value in got.items():
            # equal_nan: a model whose output overflows gives inf/NaN in both (encoder_core reports such frames)
            if value.shape != ref[name].shape or not np.allclose(value, ref[name], rtol=0.0, atol=PROBE_TOL,
                                                                 equal_nan=True):
                raise ExportDisagrees(f"its {name} differs from torch's by more than {PROBE_TOL:g} on a probe frame")

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rgb (N,64,64,3) uint8, depth (N,64,64) metres -> mu (N,L), xyz (N,3), valid (N,), float32."""
        return tuple(self.mu_xyz.run(None, {'rgb': np.ascontiguousarray(rgb, dtype=np.uint8),
                                            'depth': np.ascontiguousarray(depth, dtype=np.float32)}))

    def decode_depth(self, mu: np.ndarray) -> np.ndarray:
        """mu (N, L) -> denoised depth (N, 64, 64) float32 metres."""
        return self.depth.run(None, {'mu': np.ascontiguousarray(mu, dtype=np.float32)})[0]
