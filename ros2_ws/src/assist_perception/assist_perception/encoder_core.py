"""Pure encoder core behind encoder_node (no rclpy): image decoding, resizing, CM-VAE inference.

Images: colour rgb8/bgr8 (also rgba8/bgra8), depth 32FC1 metres or 16UC1 millimetres; invalid
depth is 0 or NaN. Any resolution is accepted: both images are centre-cropped to a square (the
training camera is square with the D435i's 58 deg vertical FOV, so cropping the sides of a wider
image keeps that FOV) and resized to 64x64 (colour: area averaging; depth: nearest neighbour so
holes stay holes and no false depth is interpolated across edges). Depth should be aligned to the
colour image (RealSense `align_depth`), as in the simulator.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import logging

import cv2
import numpy as np

from assist_common.images import COLOR_ENCODINGS, DEPTH_ENCODINGS, BadFrame, decode_color, decode_depth  # noqa: F401
from assist_common.shipped import shipped_model_path

from .errors import ModelLoadError
from .onnx_backend import OnnxCMVAE, resolve_backend

if TYPE_CHECKING:
    import torch

    from .model import CMVAE

_LOG = logging.getLogger(__name__)

_T = TypeVar('_T')


@dataclass(frozen=True)
class EncoderOutput:
    """One encoded frame."""

    mu: np.ndarray                    # (latent_dim,) float32, encoder mean
    pad_xyz: np.ndarray               # (3,) float32, camera optical frame metres
    depth: np.ndarray | None          # (64,64) float32 denoised depth (metres) when requested


def default_model_path() -> Path:
    """The shipped weights cmvae.pt: $ASSIST_MODELS_DIR, share/assist_perception/models, or the repo's models/."""
    return shipped_model_path('assist_perception', 'cmvae.pt')


def valid_fraction(depth: np.ndarray) -> np.ndarray:
    """Fraction of finite, positive pixels of (..., H, W) depth, per image (the ONNX graph computes the same)."""
    return (np.isfinite(depth) & (depth > 0)).mean(axis=(-2, -1))


MIN_FRAME_SIDE_PX = 16     # smaller frames are refused (bad_size): too few pixels to be a camera view
MAX_FRAME_ASPECT = 4.0     # frames longer than this times their short side are refused (cameras: 4:3, 16:9)


def center_square(img: np.ndarray) -> np.ndarray:
    """Centre crop to a square (the shorter side)."""
    h, w = img.shape[:2]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    return img[y0:y0 + s, x0:x0 + s]


def resize_pair(rgb: np.ndarray, depth: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Crop both images to centre squares and resize to size x size (area / nearest)."""
    rgb, depth = center_square(rgb), center_square(depth)
    if rgb.shape[:2] != (size, size):
        interp = cv2.INTER_AREA if rgb.shape[0] > size else cv2.INTER_LINEAR
        rgb = cv2.resize(rgb, (size, size), interpolation=interp)
    if depth.shape != (size, size):
        depth = cv2.resize(depth, (size, size), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(rgb), np.ascontiguousarray(depth, dtype=np.float32)


def check_device(device: str) -> torch.device:
    """Parse a torch device string and check it exists here; raises ValueError."""
    import torch
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f'unknown torch device {device!r}') from exc
    if dev.type == 'cuda' and not torch.cuda.is_available():
        raise ValueError(f'device {device!r} requested but CUDA is not available')
    if dev.type not in ('cpu', 'cuda'):
        raise ValueError(f'unsupported device {device!r} (cpu or cuda[:N])')
    return dev


class LatentEncoder:
    """Loads the CM-VAE once and encodes RGB-D frames (any resolution) to mu / pad XYZ / depth.

    On the onnxruntime backend with the export cached (onnx_backend) no torch is imported: the torch model
    (`model`) is loaded only when something asks for it."""

    def __init__(self, model_path: str | Path | None = None, device: str = 'cpu',
                 threads: int = 1, min_valid_fraction: float = 0.01, warm_up: bool = True,
                 backend: str = 'auto'):
        self.model_path = Path(model_path) if model_path else default_model_path()
        # 'cpu' is known without torch; any other device string is torch's to parse
        self.device = 'cpu' if device == 'cpu' else check_device(device)
        self.backend = resolve_backend(backend, 'cpu' if device == 'cpu' else self.device.type)
        self.threads = int(threads)
        self.min_valid_fraction = float(min_valid_fraction)
        self._model: CMVAE | None = None
        self._ort: OnnxCMVAE | None = None
        if not self.model_path.is_file():
            raise ModelLoadError(f'CM-VAE weights file not found: {self.model_path}')
        if self.backend == 'onnxruntime':
            try:
                # mu + pad XYZ (the per-frame path) and the depth decoder through ONNX Runtime: same weights
                self._ort = OnnxCMVAE(self.model_path, lambda: self.model, self.threads)
            except ModelLoadError:
                raise
            except Exception as exc:  # noqa: BLE001 - the exporter and ORT raise many types
                if backend == 'onnxruntime':
                    raise ValueError(f'CM-VAE {self.model_path}: cannot run it on onnxruntime '
                                     f'({type(exc).__name__}: {exc})') from None
                _LOG.warning('CM-VAE %s: cannot run it on onnxruntime (%s: %s); running it on torch',
                             self.model_path, type(exc).__name__, exc)
                self.backend = 'torch'
        if self._ort is not None:
            self.image_size, self._latent_dim = self._ort.image_size, self._ort.latent_dim
        else:
            self.image_size, self._latent_dim = int(self.model.cfg.image_size), int(self.model.cfg.latent_dim)
        if warm_up:
            self.warm_up()

    @property
    def model(self) -> CMVAE:
        """The torch CM-VAE (loaded on first use: the onnxruntime backend with a cached export never needs it)."""
        if self._model is None:
            import torch

            from .model import load_model
            if self.threads > 0:
                torch.set_num_threads(self.threads)
            model = load_model(self.model_path, self.device)
            # NHWC ("channels last") weights and inputs: on CPU the 64x64 convolutions and the max-pool
            # run ~2.3x faster than NCHW (bench `perception`); mu agrees with NCHW to ~1e-6
            self._model = model.to(memory_format=torch.channels_last)
        return self._model

    def warm_up(self) -> None:
        """Run every network once on a synthetic frame: the first inference allocates and picks kernels (~15 ms
        instead of ~1 ms on torch), which must not land on the first real frame."""
        s = self.image_size
        rgb = np.full((1, s, s, 3), 128, np.uint8)
        depth = np.full((1, s, s), 2.5, np.float32)
        for _ in range(2):
            mu, _, _ = self._mu_xyz(rgb, depth)
            self._depth(mu)

    def _mu_xyz(self, rgb64: np.ndarray, d64: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N,64,64,3) uint8 + (N,64,64) depth -> mu (N,L), pad XYZ (N,3), valid-depth fraction (N,)."""
        if self._ort is not None:
            return self._ort(rgb64, d64)
        import torch
        with torch.inference_mode():
            mu, _ = self.model.encode(self._input(rgb64, d64))
            xyz = self.model.decode_xyz(mu)
            return mu.cpu().numpy().astype(np.float32), xyz.cpu().numpy().astype(np.float32), valid_fraction(d64)

    def _depth(self, mu: np.ndarray) -> np.ndarray:
        """(N, L) latent means -> (N, 64, 64) float32 denoised depth in metres (unchecked)."""
        if self._ort is not None:
            return self._ort.decode_depth(mu)
        import torch
        with torch.inference_mode():
            z = torch.as_tensor(mu, device=self.device)
            return self.model.decode_depth(z).cpu().numpy().astype(np.float32)

    def _input(self, rgb64: np.ndarray, d64: np.ndarray) -> torch.Tensor:
        """Prepared 64x64 frame(s) -> the network input on the device, channels-last like the weights."""
        import torch

        from .model import preprocess
        x = preprocess(rgb64, d64, self.model.cfg)
        return x.to(self.device).contiguous(memory_format=torch.channels_last)

    @property
    def latent_dim(self) -> int:
        """Size of mu."""
        return self._latent_dim

    def _sized(self, rgb: np.ndarray, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A decoded frame checked and resized to the network's input size; raises BadFrame."""
        s = self.image_size
        if (rgb.shape == (s, s, 3) and rgb.dtype == np.uint8 and depth_m.shape == (s, s)
                and depth_m.dtype == np.float32):
            return rgb, depth_m        # already the network's size (the simulator's camera): no copies
        rgb, depth_m = np.asarray(rgb), np.asarray(depth_m)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or depth_m.ndim != 2 or 0 in rgb.shape or 0 in depth_m.shape:
            raise BadFrame('bad_size', f'rgb {rgb.shape}, depth {depth_m.shape}')
        if rgb.dtype != np.uint8:    # decode_color gives uint8; floats could carry NaN/inf into the network
            raise BadFrame('bad_encoding', f'colour array must be uint8, got {rgb.dtype}')
        if not np.issubdtype(depth_m.dtype, np.number):
            raise BadFrame('bad_encoding', f'depth array must be numeric, got {depth_m.dtype}')
        side = min(rgb.shape[:2])
        if side < MIN_FRAME_SIDE_PX or max(rgb.shape[:2]) > MAX_FRAME_ASPECT * side:
            # a 1x1 or 4096x2 frame is not a camera view: centre-cropped and resized it would still make a latent
            raise BadFrame('bad_size', f'frame {rgb.shape[1]}x{rgb.shape[0]}: want at least {MIN_FRAME_SIDE_PX} '
                           f'pixels a side and an aspect ratio within {MAX_FRAME_ASPECT:g}:1')
        ar_rgb = rgb.shape[1] / rgb.shape[0]
        ar_d = depth_m.shape[1] / depth_m.shape[0]
        if abs(ar_rgb - ar_d) > 0.02:
            raise BadFrame('size_mismatch', f'rgb {rgb.shape[1]}x{rgb.shape[0]} vs depth '
                           f'{depth_m.shape[1]}x{depth_m.shape[0]} (depth must be aligned to colour)')
        return resize_pair(rgb, depth_m, s)

    def _check_valid(self, fraction: float) -> None:
        """BadFrame('no_valid_depth') when too few depth pixels are valid to encode."""
        if fraction < self.min_valid_fraction:
            raise BadFrame('no_valid_depth', f'{fraction:.1%} valid depth pixels')

    def prepare(self, rgb: np.ndarray, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validate and resize a decoded frame; raises BadFrame."""
        rgb64, d64 = self._sized(rgb, depth_m)
        self._check_valid(float(valid_fraction(d64)))
        return rgb64, d64

    def encode(self, rgb: np.ndarray, depth_m: np.ndarray, want_depth: bool = False,
               want_xyz: bool = True) -> EncoderOutput:
        """Encode one frame (uint8 RGB HxWx3, depth metres HxW); raises BadFrame.

        The decoders run only when asked: `want_xyz` for the pad estimate, `want_depth` for the
        denoised depth image (the policy needs only mu); pad_xyz is NaN when not computed."""
        rgb64, d64 = self._sized(rgb, depth_m)
        mu, xyz, valid = self._mu_xyz(rgb64[None], d64[None])   # the XYZ head is a few us: always run
        self._check_valid(float(valid[0]))
        mu, xyz = mu[0], (xyz[0] if want_xyz else np.full(3, np.nan, np.float32))
        if not (np.isfinite(mu).all() and (not want_xyz or np.isfinite(xyz).all())):
            raise BadFrame('nonfinite_output', 'the model produced non-finite values for this frame')
        depth = self.decode_depth(mu) if want_depth else None
        return EncoderOutput(mu, xyz, depth)

    def decode_depth(self, mu: np.ndarray) -> np.ndarray:
        """Denoised depth (64x64 float32 metres) of one latent mean (after publishing mu); raises BadFrame."""
        depth = self._depth(np.asarray(mu, np.float32)[None])[0]
        if not np.all(np.isfinite(depth)):
            raise BadFrame('nonfinite_output', 'the depth decoder produced non-finite values')
        return depth

    def encode_mu_batch(self, rgbs: list[np.ndarray], depths: list[np.ndarray]) -> np.ndarray:
        """mu of N frames in one forward pass (vectorised environments): (N, latent_dim) float32.

        Every frame must pass `prepare`; raises BadFrame naming the first bad frame's index."""
        if len(rgbs) != len(depths):
            raise ValueError(f'{len(rgbs)} colour frames but {len(depths)} depth frames')
        if not rgbs:
            return np.zeros((0, self.latent_dim), np.float32)
        prepared = []
        for i, (rgb, depth) in enumerate(zip(rgbs, depths)):
            try:
                prepared.append(self.prepare(rgb, depth))
            except BadFrame as exc:
                raise BadFrame(exc.reason, f'frame {i}: {exc}') from exc
        mu, _, _ = self._mu_xyz(np.stack([p[0] for p in prepared]), np.stack([p[1] for p in prepared]))
        bad = ~np.isfinite(mu).all(axis=1)
        if bad.any():
            raise BadFrame('nonfinite_output', f'frame {int(np.flatnonzero(bad)[0])}: the model produced '
                                               'non-finite values')
        return mu


class LatestOnly(Generic[_T]):
    """One-slot mailbox: put() replaces an unread item (counted), take() waits for a new one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: _T | None = None
        self._closed = False
        self.replaced = 0

    def put(self, item: _T) -> None:
        """Store `item`, dropping any unread older one."""
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float | None = None) -> _T | None:
        """Newest unread item, or None on timeout / close."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        """Wake any waiter; later take() calls return immediately."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """True after close()."""
        return self._closed


class StampPairer:
    """Approximate time sync of two streams: pairs each new message with the other stream's
    latest one when their stamps differ by at most `slop_s` (each message is used once)."""

    def __init__(self, slop_s: float):
        self.slop_s = float(slop_s)
        self._lock = threading.Lock()
        self._latest: dict[str, tuple[float, Any] | None] = {'color': None, 'depth': None}
        self.unpaired = 0     # messages replaced before a partner within the slop arrived

    def add(self, stream: str, stamp: float, msg: Any) -> tuple[Any, Any] | None:
        """Offer a message of stream 'color' or 'depth'; returns (color, depth) when they pair."""
        other = 'depth' if stream == 'color' else 'color'
        with self._lock:
            o = self._latest[other]
            if o is not None and abs(o[0] - stamp) <= self.slop_s:
                if self._latest[stream] is not None:
                    self.unpaired += 1
                self._latest[other] = None
                self._latest[stream] = None
                return (msg, o[1]) if stream == 'color' else (o[1], msg)
            if self._latest[stream] is not None:
                self.unpaired += 1
            self._latest[stream] = (stamp, msg)
            return None
