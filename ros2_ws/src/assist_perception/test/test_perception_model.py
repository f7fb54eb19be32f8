"""CM-VAE shapes, KL against the closed form, masked XYZ loss, weights file loading."""
import math

import numpy as np
import pytest
import torch

from assist_perception.model import (CMVAE, CMVAEConfig, LossConfig, ModelLoadError, cmvae_loss,
                                     kl_divergence, latent_interpolation, load_model, preprocess,
                                     reparameterize, save_model)


@pytest.fixture(scope='module')
def model():
    torch.manual_seed(0)
    return CMVAE(CMVAEConfig(latent_dim=10)).eval()


def test_shapes_and_scalar_decoders_read_single_latents(model):
    x = torch.rand(5, 4, 64, 64)
    out = model(x)
    assert out.mu.shape == (5, 10) and out.logvar.shape == (5, 10) and out.z.shape == (5, 10)
    assert out.depth.shape == (5, 64, 64) and out.xyz.shape == (5, 3)
    z = torch.randn(4, 10)
    base = model.decode_xyz(z)
    z2 = z.clone()
    z2[:, 3:] += 5.0                      # p_X,p_Y,p_Z ignore z[3:]
    torch.testing.assert_close(model.decode_xyz(z2), base)
    z3 = z.clone()
    z3[:, 1] += 1.0                       # changing z[1] moves only Y
    moved = model.decode_xyz(z3)
    torch.testing.assert_close(moved[:, [0, 2]], base[:, [0, 2]])
    assert not torch.allclose(moved[:, 1], base[:, 1])
    assert not torch.allclose(model.decode_depth(z2), model.decode_depth(z))   # p_D uses all of z
    det = model(x, sample=False)
    torch.testing.assert_close(det.z, det.mu)


def test_kl_matches_closed_form_and_torch_distributions():
    mu = torch.tensor([[1.0, 0.0], [0.0, 0.0]])
    logvar = torch.tensor([[0.0, 0.0], [math.log(4.0), 0.0]])
    # KL(N(1,1)||N(0,1)) = 0.5; KL(N(0,4)||N(0,1)) = 0.5 (4 - 1 - ln 4)
    expected = torch.tensor([0.5, 0.5 * (4.0 - 1.0 - math.log(4.0))])
    torch.testing.assert_close(kl_divergence(mu, logvar), expected)
    g = torch.Generator().manual_seed(1)
    mu = torch.randn(64, 10, generator=g)
    logvar = torch.randn(64, 10, generator=g)
    ref = torch.distributions.kl_divergence(
        torch.distributions.Normal(mu, torch.exp(0.5 * logvar)),
        torch.distributions.Normal(torch.zeros_like(mu), torch.ones_like(mu))).sum(1)
    torch.testing.assert_close(kl_divergence(mu, logvar), ref)
    assert float(kl_divergence(torch.zeros(3, 10), torch.zeros(3, 10)).abs().max()) == 0.0


def test_reparameterisation_has_the_right_moments():
    torch.manual_seed(2)
    mu = torch.full((200_000, 1), 1.5)
    logvar = torch.full((200_000, 1), math.log(0.25))
    z = reparameterize(mu, logvar)
    assert abs(float(z.mean()) - 1.5) < 0.01 and abs(float(z.std()) - 0.5) < 0.01


def test_loss_weights_and_masking(model):
    cfg = LossConfig(w_depth=1.0, w_xyz=2.0, w_kl=4.0, depth_sigma_m=0.5, xyz_sigma_m=0.1)
    with torch.no_grad():
        out = model(torch.rand(4, 4, 64, 64), sample=False)
    depth = out.depth + 0.5             # error 0.5 m = 1 sigma per pixel
    xyz = out.xyz.clone()
    xyz[0, 0] += 0.2                             # visible frame: (0.2/0.1)^2 = 4
    xyz[1] += 100.0                              # invisible frame: ignored
    vis = torch.tensor([True, False, True, True])
    t = cmvae_loss(out, depth, xyz, vis, cfg)
    assert float(t.depth) == pytest.approx(64 * 64, rel=1e-5)
    assert float(t.xyz) == pytest.approx(4.0 / 4, rel=1e-4)    # divided by the full batch
    kl = float(kl_divergence(out.mu, out.logvar).mean())
    assert float(t.kl) == pytest.approx(kl, rel=1e-6)
    assert float(t.total) == pytest.approx(4096 + 2 * 1.0 + 4 * kl, rel=1e-5)
    warm = cmvae_loss(out, depth, xyz, vis, cfg, kl_scale=0.0)
    assert float(warm.total) == pytest.approx(4096 + 2.0, rel=1e-5)


def test_preprocess_scales_and_clears_holes():
    cfg = CMVAEConfig()
    rgb = np.full((64, 64, 3), 255, np.uint8)
    d = np.full((64, 64), 2.5, np.float32)
    d[0, 0], d[0, 1], d[0, 2] = np.nan, -1.0, 50.0
    x = preprocess(rgb, d, cfg)
    assert x.shape == (1, 4, 64, 64)
    assert float(x[0, :3].min()) == 1.0
    assert float(x[0, 3, 5, 5]) == pytest.approx(2.5 / cfg.depth_scale_m)
    assert x[0, 3, 0, :3].tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError):
        preprocess(np.zeros((32, 32, 3), np.uint8), np.zeros((32, 32)), cfg)


def test_save_load_roundtrip_and_clear_errors(model, tmp_path):
    model.set_xyz_stats(np.array([0.1, -0.2, 2.0]), np.array([0.8, 1.0, 0.9]))
    path = tmp_path / 'm.pt'
    save_model(path, model, {'note': 'test'})
    loaded = load_model(path)
    assert loaded.cfg == model.cfg and loaded.metadata['note'] == 'test'
    x = torch.rand(2, 4, 64, 64)
    a, b = model(x, sample=False), loaded(x, sample=False)
    torch.testing.assert_close(a.depth, b.depth)
    torch.testing.assert_close(a.xyz, b.xyz)
    with pytest.raises(ModelLoadError, match='not found'):
        load_model(tmp_path / 'missing.pt')
    bad = tmp_path / 'corrupt.pt'
    bad.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ModelLoadError, match='cannot read'):
        load_model(bad)
    other = tmp_path / 'other.pt'
    torch.save({'weights': torch.zeros(3)}, other)
    with pytest.raises(ModelLoadError, match='not a CM-VAE'):
        load_model(other)
    wrong = tmp_path / 'wrong.pt'
    payload = torch.load(path, weights_only=True)
    payload['config']['latent_dim'] = 12
    torch.save(payload, wrong)
    with pytest.raises(ModelLoadError, match='do not match'):
        load_model(wrong)


def test_pickled_code_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ('pwned',))
    path = tmp_path / 'evil.pt'
    torch.save({'format': 'x', 'obj': Evil()}, path)
    with pytest.raises(ModelLoadError, match='cannot read'):
        load_model(path)


def test_latent_interpolation_ends_match_reconstructions(model):
    x1, x2 = torch.rand(4, 64, 64), torch.rand(4, 64, 64)
    seq = latent_interpolation(model, x1, x2, steps=5)
    assert seq.shape == (5, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(seq[0], model(x1[None], sample=False).depth[0])
        torch.testing.assert_close(seq[-1], model(x2[None], sample=False).depth[0])
