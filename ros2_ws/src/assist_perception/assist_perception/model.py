"""Denoising cross-modal VAE (CM-VAE): the one model definition used by training, evaluation and the node.

Input x_RGBD: 4 x 64 x 64 (RGB in [0,1], depth in metres / `depth_scale_m`, holes 0).
Encoder q_RGBD: DroNet (conv 5x5/2, max-pool 3x3/2, three residual blocks of 32/64/128 channels)
-> mean mu and log-variance of a diagonal Gaussian over z (size `latent_dim`).
Decoders: p_D(z) -> 64 x 64 denoised depth (metres); p_X(z[0]), p_Y(z[1]), p_Z(z[2]) -> the closest
visible pad's top-centre in the camera optical frame (metres; x right, y down, z out of the lens).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from assist_common.atomic import atomic_path
from assist_common.settings import SettingsError, check_named, setting

from .errors import ModelLoadError

MODEL_FORMAT = 'assist_perception.cmvae'
MODEL_VERSION = 1
MAX_RANGE_M = 1000.0      # no depth scale, depth limit or pad coordinate of a downward camera exceeds this


def _plain(v: Any) -> Any:
    """A weights file's value as plain Python: numpy scalars as numbers, lists as tuples (strings as they are)."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple, np.ndarray)):
        return tuple(_plain(x) for x in v)
    return v


@dataclass
class CMVAEConfig:
    """Architecture and input/output scaling of the CM-VAE (stored inside every weights file)."""

    latent_dim: int = setting(10, ge=3, le=4096)      # CM-VAE reference size: z[0:3] = pad XYZ (p_X, p_Y, p_Z)
    image_size: int = setting(64, choices=(64,))     # the decoder is built for 64x64 images
    channels: tuple[int, int, int] = setting((32, 64, 128), ge=1, le=1024)   # DroNet residual blocks
    depth_scale_m: float = setting(5.0, gt=0.0, le=MAX_RANGE_M)     # network depth units: metres / depth_scale_m
    max_input_depth_m: float = setting(10.0, gt=0.0, le=MAX_RANGE_M)   # farther depth readings are holes
    init_depth_m: float = setting(2.5, ge=0.0, le=MAX_RANGE_M)   # initial output of p_D (training starts near it)
    xyz_hidden: int = setting(64, ge=1, le=8192)     # width of each scalar decoder p_X, p_Y, p_Z
    # label standardisation (from data)
    xyz_mean: tuple[float, float, float] = setting((0.0, 0.0, 2.0), ge=-MAX_RANGE_M, le=MAX_RANGE_M)
    xyz_std: tuple[float, float, float] = setting((1.0, 1.0, 1.0), gt=0.0, le=MAX_RANGE_M)

    def __post_init__(self) -> None:
        """Validate types, lengths and ranges (a weights file's config passes through here); ValueError, one line."""
        for f in dataclasses.fields(self):
            setattr(self, f.name, _plain(getattr(self, f.name)))
        check_named(self, 'CMVAEConfig')
        for name in ('depth_scale_m', 'max_input_depth_m', 'init_depth_m'):
            setattr(self, name, float(getattr(self, name)))
        self.xyz_mean, self.xyz_std = tuple(map(float, self.xyz_mean)), tuple(map(float, self.xyz_std))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CMVAEConfig:
        """Build from a plain dict (as stored in a weights file); unknown keys raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f'unknown CMVAEConfig keys {sorted(unknown)}')
        return cls(**data)


@dataclass
class LossConfig:
    """Weights of the three CM-VAE losses (paper: depth 1, pad XYZ 2, KL 4) and their units.

    The paper gives weights but not reductions. Here every term is per-sample and averaged over
    the batch: the depth term is the sum over the 64x64 pixels of (error / depth_sigma_m)^2, the
    XYZ term the sum over the three axes of (error / xyz_sigma_m)^2, and the KL term the exact
    KL(N(mu, sigma^2) || N(0, I)) summed over latent dims (nats). Frames without a visible pad
    contribute 0 to the XYZ term (masked), and the term is still divided by the full batch size
    so each visible frame weighs the same whatever the batch composition.
    """

    w_depth: float = 1.0
    w_xyz: float = 2.0
    w_kl: float = 4.0
    depth_sigma_m: float = 0.25
    xyz_sigma_m: float = 0.03


class CMVAEOutput(NamedTuple):
    """Everything one forward pass produces."""

    mu: torch.Tensor          # (N, L)
    logvar: torch.Tensor      # (N, L)
    z: torch.Tensor           # (N, L) sample (or mu when not sampling)
    depth: torch.Tensor       # (N, 64, 64) metres
    xyz: torch.Tensor         # (N, 3) metres, camera optical frame


class _ResBlock(nn.Module):
    """DroNet residual block: BN-ReLU-conv3x3/2, BN-ReLU-conv3x3, plus a 1x1/2 conv shortcut."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.bn1 = nn.BatchNorm2d(cin)
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=2, padding=1)
        self.bn2 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Residual step, halving the resolution."""
        y = self.conv1(F.relu(self.bn1(x)))
        y = self.conv2(F.relu(self.bn2(y)))
        return y + self.skip(x)


class DroNetEncoder(nn.Module):
    """q_RGBD: 4x64x64 -> (mu, logvar), DroNet / ResNet-8 trunk."""

    def __init__(self, cfg: CMVAEConfig):
        super().__init__()
        c1, c2, c3 = cfg.channels
        self.conv = nn.Conv2d(4, c1, 5, stride=2, padding=2)          # 64 -> 32
        self.pool = nn.MaxPool2d(3, stride=2, padding=1)                # 32 -> 16
        self.blocks = nn.Sequential(_ResBlock(c1, c1), _ResBlock(c1, c2), _ResBlock(c2, c3))  # -> 2
        self.head = nn.Linear(c3 * 2 * 2, 2 * cfg.latent_dim)
        self.latent_dim = cfg.latent_dim

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return (mu, logvar), each (N, latent_dim)."""
        h = self.blocks(self.pool(self.conv(x)))
        out = self.head(F.relu(torch.flatten(h, 1)))
        return out[:, :self.latent_dim], out[:, self.latent_dim:]


class DepthDecoder(nn.Module):
    """p_D: full z -> 64x64 depth in network units (metres / depth_scale_m)."""

    def __init__(self, cfg: CMVAEConfig):
        super().__init__()
        self.fc = nn.Linear(cfg.latent_dim, 128 * 4 * 4)
        self.net = nn.Sequential(
            nn.ConvTranspose2d(128, 64, 4, stride=2, padding=1), nn.ReLU(),   # 8
            nn.ConvTranspose2d(64, 32, 4, stride=2, padding=1), nn.ReLU(),    # 16
            nn.ConvTranspose2d(32, 16, 4, stride=2, padding=1), nn.ReLU(),    # 32
            nn.ConvTranspose2d(16, 1, 4, stride=2, padding=1),                # 64
        )
        with torch.no_grad():   # start at a typical depth (2.5 m) instead of 0
            self.net[-1].bias.fill_(cfg.init_depth_m / cfg.depth_scale_m)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Return (N, 64, 64)."""
        h = F.relu(self.fc(z)).view(-1, 128, 4, 4)
        return self.net(h)[:, 0]


class ScalarDecoder(nn.Module):
    """p_X / p_Y / p_Z: one latent element -> one standardised coordinate."""

    def __init__(self, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(1, hidden), nn.ReLU(), nn.Linear(hidden, hidden),
                                 nn.ReLU(), nn.Linear(hidden, 1))

    def forward(self, z1: torch.Tensor) -> torch.Tensor:
        """(N, 1) -> (N,)."""
        return self.net(z1)[:, 0]


class CMVAE(nn.Module):
    """Denoising CM-VAE: noisy RGB-D in, clean depth and closest-pad XYZ out."""

    def __init__(self, cfg: CMVAEConfig | None = None):
        super().__init__()
        self.cfg = cfg or CMVAEConfig()
        self.encoder = DroNetEncoder(self.cfg)
        self.depth_decoder = DepthDecoder(self.cfg)
        self.xyz_decoders = nn.ModuleList(ScalarDecoder(self.cfg.xyz_hidden) for _ in range(3))
        self.register_buffer('xyz_mean', torch.tensor(self.cfg.xyz_mean, dtype=torch.float32))
        self.register_buffer('xyz_std', torch.tensor(self.cfg.xyz_std, dtype=torch.float32))

    def set_xyz_stats(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Set the label standardisation (config and buffers) from training-set statistics."""
        mean = np.asarray(mean, dtype=np.float32).reshape(3)
        std = np.maximum(np.asarray(std, dtype=np.float32).reshape(3), 1e-3)
        self.cfg.xyz_mean = tuple(float(v) for v in mean)
        self.cfg.xyz_std = tuple(float(v) for v in std)
        self.xyz_mean.copy_(torch.from_numpy(mean))
        self.xyz_std.copy_(torch.from_numpy(std))

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """q_RGBD(x) -> (mu, logvar)."""
        return self.encoder(x)

    def decode_depth(self, z: torch.Tensor) -> torch.Tensor:
        """p_D(z) -> (N, 64, 64) depth in metres."""
        return self.depth_decoder(z) * self.cfg.depth_scale_m

    def decode_xyz(self, z: torch.Tensor) -> torch.Tensor:
        """(p_X(z0), p_Y(z1), p_Z(z2)) -> (N, 3) metres in the camera optical frame."""
        std = torch.stack([dec(z[:, i:i + 1]) for i, dec in enumerate(self.xyz_decoders)], dim=1)
        return std * self.xyz_std + self.xyz_mean

    def forward(self, x: torch.Tensor, sample: bool = True) -> CMVAEOutput:
        """Encode, draw z = mu + sigma * eps (or z = mu when `sample` is False), decode."""
        mu, logvar = self.encode(x)
        z = reparameterize(mu, logvar) if sample else mu
        return CMVAEOutput(mu, logvar, z, self.decode_depth(z), self.decode_xyz(z))


def reparameterize(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """z = mu + exp(logvar / 2) * eps, eps ~ N(0, I)."""
    return mu + torch.exp(0.5 * logvar) * torch.randn_like(mu)


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """Per-sample KL(N(mu, exp(logvar)) || N(0, I)) in nats, summed over latent dims -> (N,)."""
    return 0.5 * torch.sum(torch.exp(logvar) + mu * mu - 1.0 - logvar, dim=1)


class LossTerms(NamedTuple):
    """Total loss and its parts (batch means)."""

    total: torch.Tensor
    depth: torch.Tensor
    xyz: torch.Tensor
    kl: torch.Tensor


def cmvae_loss(out: CMVAEOutput, depth_clean: torch.Tensor, xyz: torch.Tensor,
               visible: torch.Tensor, cfg: LossConfig, kl_scale: float = 1.0) -> LossTerms:
    """Weighted CM-VAE loss; `visible` (N,) masks the XYZ term; `kl_scale` is a warm-up factor."""
    n = depth_clean.shape[0]
    d = ((out.depth - depth_clean) / cfg.depth_sigma_m).pow(2).reshape(n, -1).sum(1).mean()
    per = ((out.xyz - xyz) / cfg.xyz_sigma_m).pow(2).sum(1)
    x = torch.where(visible.bool(), per, torch.zeros_like(per)).sum() / n
    kl = kl_divergence(out.mu, out.logvar).mean()
    total = cfg.w_depth * d + cfg.w_xyz * x + cfg.w_kl * kl_scale * kl
    return LossTerms(total, d, x, kl)


def preprocess_tensor(rgb: torch.Tensor, depth_m: torch.Tensor, cfg: CMVAEConfig) -> torch.Tensor:
    """uint8 RGB (N,H,W,3) + metric depth (N,H,W) tensors, holes 0/NaN -> float (N,4,H,W) network input.

    The one definition of the input scaling: `preprocess` (training, evaluation, torch inference)
    calls it, and the ONNX Runtime encoder exports it into its graph."""
    depth = depth_m.to(torch.float32)
    keep = torch.isfinite(depth) & (depth > 0) & (depth <= cfg.max_input_depth_m)
    d = torch.where(keep, depth, torch.zeros((), dtype=torch.float32))
    rgbf = rgb.permute(0, 3, 1, 2).to(torch.float32) / 255.0
    return torch.cat([rgbf, (d / cfg.depth_scale_m).unsqueeze(1)], dim=1)


def preprocess(rgb: np.ndarray, depth_m: np.ndarray, cfg: CMVAEConfig) -> torch.Tensor:
    """uint8 RGB (N,64,64,3) + metric depth (N,64,64), holes 0/NaN -> float tensor (N,4,64,64)."""
    rgb = np.asarray(rgb)
    depth = np.asarray(depth_m, dtype=np.float32)
    if rgb.ndim == 3:
        rgb, depth = rgb[None], depth[None]
    s = cfg.image_size
    if rgb.shape[1:] != (s, s, 3) or depth.shape[1:] != (s, s) or rgb.shape[0] != depth.shape[0]:
        raise ValueError(f'expected RGB (N,{s},{s},3) and depth (N,{s},{s}), '
                         f'got {rgb.shape} and {depth.shape}')
    return preprocess_tensor(torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.uint8)),
                             torch.from_numpy(np.ascontiguousarray(depth)), cfg)


def save_model(path: str | Path, model: CMVAE, metadata: dict[str, Any] | None = None) -> None:
    """Write weights + config + metadata as a plain dict of tensors/primitives (weights_only safe)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        'format': MODEL_FORMAT,
        'version': MODEL_VERSION,
        'config': dataclasses.asdict(model.cfg),
        'state_dict': {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        'metadata': dict(metadata or {}),
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def load_training_state(path: str | Path, keys: tuple[str, ...]) -> dict:
    """A training checkpoint (weights_only) holding `keys`; ValueError (one line) when it is damaged."""
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types (pickle, zip, runtime, EOF) for damaged files
        first = (str(exc).strip().splitlines() or [''])[0][:200]
        raise ValueError(f'damaged checkpoint {path}: {type(exc).__name__}: {first}') from None
    missing = [k for k in keys if not isinstance(state, dict) or k not in state]
    if missing:
        raise ValueError(f'damaged checkpoint {path}: lacks {", ".join(missing)}')
    return state


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:200]


def load_model(path: str | Path, device: str | torch.device = 'cpu') -> CMVAE:
    """Load a CM-VAE saved by `save_model` (weights_only=True); any problem -> ModelLoadError."""
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(f'CM-VAE weights file not found: {path}')
    try:
        payload = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types (pickle, zip, runtime) for bad files
        raise ModelLoadError(f'cannot read CM-VAE weights {path}: {type(exc).__name__} (not a torch '
                             'weights file, truncated, or holding objects that weights_only=True '
                             'refuses)') from None
    if not isinstance(payload, dict) or payload.get('format') != MODEL_FORMAT:
        raise ModelLoadError(f'{path} is not a CM-VAE weights file (format tag missing)')
    if payload.get('version') != MODEL_VERSION:
        raise ModelLoadError(f'{path}: unsupported CM-VAE file version {payload.get("version")}')
    try:
        if not isinstance(payload.get('config'), dict):
            raise ValueError("no 'config' dict")
        cfg = CMVAEConfig.from_dict(dict(payload['config']))
    except (TypeError, ValueError) as exc:
        raise ModelLoadError(f'{path}: bad CM-VAE config: {_first_line(exc)}') from None
    try:
        model = CMVAE(cfg)
        model.load_state_dict(payload['state_dict'])
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise ModelLoadError(f'{path}: weights do not match the CM-VAE definition: {_first_line(exc)}') from None
    for name, t in model.state_dict().items():
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise ModelLoadError(f'{path}: non-finite values in {name}')
    if not bool(((model.xyz_std > 0) & (model.xyz_std <= MAX_RANGE_M)).all()
                and (model.xyz_mean.abs() <= MAX_RANGE_M).all()):
        raise ModelLoadError(f'{path}: xyz_std must be in (0, {MAX_RANGE_M:g}] and xyz_mean within '
                             f'+-{MAX_RANGE_M:g}, got {model.xyz_std.tolist()}, {model.xyz_mean.tolist()}')
    metadata = payload.get('metadata', {})
    if not isinstance(metadata, dict):
        raise ModelLoadError(f'{path}: metadata must be a dict, got {type(metadata).__name__}')
    model.metadata = dict(metadata)
    return model.to(device).eval()


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def latent_interpolation(model: CMVAE, x1: torch.Tensor, x2: torch.Tensor,
                         steps: int = 8) -> torch.Tensor:
    """Depth decoded along mu_i = mu_1 + delta (mu_2 - mu_1), delta in [0, 1] -> (steps, 64, 64)."""
    with torch.no_grad():
        mu1, _ = model.encode(x1[None] if x1.dim() == 3 else x1)
        mu2, _ = model.encode(x2[None] if x2.dim() == 3 else x2)
        delta = torch.linspace(0.0, 1.0, steps, device=mu1.device)[:, None]
        return model.decode_depth(mu1 + delta * (mu2 - mu1))


__all__ = ['CMVAE', 'CMVAEConfig', 'CMVAEOutput', 'LossConfig', 'LossTerms', 'ModelLoadError',
           'cmvae_loss', 'count_parameters', 'kl_divergence', 'latent_interpolation', 'load_model',
           'preprocess', 'reparameterize', 'save_model', 'MODEL_FORMAT', 'MODEL_VERSION']


def training_device(choice: str) -> str:
    """'cuda' or 'cpu' for a training script's --device (auto: cuda when torch sees a GPU); SettingsError for cuda
    without one (said before any work)."""
    if choice == 'auto':
        return 'cuda' if torch.cuda.is_available() else 'cpu'
    if choice == 'cuda' and not torch.cuda.is_available():
        raise SettingsError('--device cuda: torch sees no CUDA GPU here (use --device cpu or auto)')
    return choice
