"""Command lines: dataclass flags, --config YAML precedence, shipped config files parse."""
import dataclasses
import json
from pathlib import Path

import pytest

from assist_common.settings import check_settings, load_yaml_settings, parse_settings
from assist_lab import cmvae_dataset as dataset, cmvae_evaluate as evaluate, cmvae_train as train

CONFIG = Path(__file__).resolve().parents[1] / 'config'


def test_flags_override_yaml_override_defaults(tmp_path):
    y = tmp_path / 't.yaml'
    y.write_text('epochs: 3\nlr: 0.01\nresume: true\n')
    cfg, _ = parse_settings(train.TrainConfig, 'x', ['--config', str(y), '--lr', '0.5'])
    assert (cfg.epochs, cfg.lr, cfg.resume, cfg.batch_size) == (3, 0.5, True, 128)
    cfg, _ = parse_settings(train.TrainConfig, 'x', ['--resume', '--batch-size', '7'])
    assert cfg.resume is True and cfg.batch_size == 7
    y.write_text('epochz: 3\n')
    with pytest.raises(SystemExit) as stop:       # one error: line naming the unknown setting, exit 2
        parse_settings(train.TrainConfig, 'x', ['--config', str(y)])
    assert stop.value.code == 2
    with pytest.raises(SystemExit):
        parse_settings(train.TrainConfig, 'x', ['--epochs', 'many'])


@pytest.mark.parametrize('name, cls', [('make_dataset.yaml', dataset.DatasetConfig),
                                       ('train_cmvae.yaml', train.TrainConfig),
                                       ('evaluate_cmvae.yaml', evaluate.EvalConfig)])
def test_shipped_config_files_are_valid(name, cls):
    cfg = cls(**load_yaml_settings(cls, CONFIG / name))
    assert dataclasses.asdict(cfg)
    check_settings(cfg)                     # every value within its rule


def test_make_dataset_main_small_set(tmp_path, capsys):
    out = tmp_path / 'd'
    assert dataset.main(['--out-dir', str(out), '--frames', '60', '--no-progress']) == 0
    text = capsys.readouterr().out
    summary = json.loads(text[text.index('{'):])
    assert summary['generated'] == 60 and summary['frames_per_s'] > 0
    assert 0.0 <= summary['visible_fraction'] <= 1.0
    assert len(list(out.glob('shard_*.npz'))) == 1
