"""Fault injection, encoder_node start-up: a weights file that loads under weights_only but holds bad
data (non-finite weights, a NaN depth scale, a wrong-length label scale) exits 1 with one clear line.
"""
from __future__ import annotations

import math

import pytest
import torch

from assist_perception.model import CMVAE, CMVAEConfig, save_model

pytestmark = pytest.mark.graph


@pytest.mark.parametrize('damage', ['nan_weight', 'nan_depth_scale', 'short_xyz_std'])
def test_bad_cmvae_file_exits_with_one_line(start_node, wait, tmp_path, damage):
    path = tmp_path / f'{damage}.pt'
    save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval())
    payload = torch.load(path, weights_only=True)
    if damage == 'nan_weight':
        payload['state_dict']['encoder.head.weight'][0, 0] = math.nan
    elif damage == 'nan_depth_scale':
        payload['config']['depth_scale_m'] = math.nan
    else:
        payload['config']['xyz_std'] = (1.0, 1.0)
    torch.save(payload, path)
    node = start_node('encoder_node', {'model_path': str(path)})
    assert wait(lambda: node.proc.poll() is not None, 90), node.log()
    log = node.log()
    errors = [ln for ln in log.splitlines() if ln.startswith('error:')]
    assert node.proc.returncode == 1 and len(errors) == 1 and str(path) in errors[0], log
    assert 'Traceback' not in log and 'weights_only' not in log, log
