"""The shipped CM-VAE meets the metrics in its card on a fresh held-out set generated here."""
import json

import numpy as np
import pytest

from assist_lab.cmvae_dataset import DatasetConfig, load_frames, make_dataset
from assist_perception.encoder_core import default_model_path
from assist_lab.cmvae_evaluate import compute_metrics
from assist_perception.model import load_model


@pytest.fixture(scope='module')
def card():
    path = default_model_path().with_name('cmvae.metrics.json')
    return json.loads(path.read_text())


@pytest.fixture(scope='module')
def fresh(tmp_path_factory, card):
    out = tmp_path_factory.mktemp('fresh')
    # a seed the training set never used: unseen scenes
    make_dataset(DatasetConfig(out_dir=str(out), frames=400, scenes_per_shard=8,
                               seed=card['test']['fresh_seed']), progress=False)
    return load_frames(out)


def test_shipped_model_meets_card_metrics(card, fresh):
    model = load_model(default_model_path())
    assert model.cfg.latent_dim == card['latent_dim']
    m = compute_metrics(model, fresh, np.arange(len(fresh)), noise_seed=card['test']['noise_seed'])
    bounds = card['test']['max']
    failures = {k: (m[k], b) for k, b in bounds.items() if not m[k] <= b}
    assert not failures, f'metric (measured, card bound): {failures}'
    # denoising: the reconstruction is much closer to clean depth than the noisy input is
    assert m['depth_rmse_m'] < 0.5 * m['noisy_input_rmse_m']
    assert m['frames_with_pad'] > 100
