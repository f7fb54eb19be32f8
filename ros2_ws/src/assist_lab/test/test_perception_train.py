"""Training smoke test: tiny real dataset, loss goes down, seeded, checkpoints resume."""
import csv

import pytest
import torch

from assist_lab.cmvae_dataset import DatasetConfig, load_frames, make_dataset
from assist_perception.model import load_model
from assist_common.settings import SettingsError
from assist_lab.cmvae_train import TrainConfig, train


@pytest.fixture(scope='module')
def frames(tmp_path_factory):
    out = tmp_path_factory.mktemp('ds')
    make_dataset(DatasetConfig(out_dir=str(out), frames=240, frames_per_scene=40, scenes_per_shard=3,
                               seed=3), progress=False)
    return load_frames(out)


def _cfg(run_dir, **kw) -> TrainConfig:
    base = dict(run_dir=str(run_dir), epochs=8, batch_size=32, lr=2e-3, warmup_steps=5,
                val_fraction=0.17, kl_warmup_epochs=1.0, seed=1)
    base.update(kw)
    return TrainConfig(**base)


def _rows(run_dir):
    with open(run_dir / 'metrics.csv', newline='') as fh:
        return list(csv.DictReader(fh))


def test_loss_goes_down_and_files_are_written(frames, tmp_path):
    run = tmp_path / 'run'
    train(_cfg(run), frames=frames, progress=False)
    rows = _rows(run)
    assert [int(r['epoch']) for r in rows] == list(range(1, 9))
    first, last = rows[0], rows[-1]
    # 8 epochs on 240 frames: the seeded run lands at 0.30-0.47 of the first epoch's depth loss here (seeds 1-3) and
    # at 0.53 on another CPU (float results differ across machines); 0.75 holds on every machine, and a broken
    # loss, optimiser or data path stays near 1
    assert float(last['train_depth_loss']) < 0.75 * float(first['train_depth_loss'])
    assert float(last['val_depth_rmse_m']) < float(first['val_depth_rmse_m'])
    assert float(last['val_loss']) < float(first['val_loss'])
    for name in ('config.json', 'checkpoint.pt', 'best.pt', 'model.pt'):
        assert (run / name).is_file()
    assert (run / 'learning_curve.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    model = load_model(run / 'model.pt')
    assert model.metadata['epoch'] == 8 and model.metadata['val_frames'] > 0


def test_seeded_and_resumable(frames, tmp_path):
    a, b = tmp_path / 'a', tmp_path / 'b'
    train(_cfg(a, epochs=2), frames=frames, progress=False)
    # b: the same run stopped after epoch 1, then resumed -> identical to the uninterrupted run
    train(_cfg(b, epochs=2, stop_after_epoch=1), frames=frames, progress=False)
    assert len(_rows(b)) == 1
    with pytest.raises(SettingsError, match='--resume'):      # a run directory with a checkpoint needs --resume
        train(_cfg(b, epochs=2), frames=frames, progress=False)
    train(_cfg(b, epochs=2, resume=True), frames=frames, progress=False)
    ra, rb = _rows(a), _rows(b)
    assert len(rb) == 2
    for key in ('train_loss', 'val_loss', 'val_depth_rmse_m'):
        assert float(rb[1][key]) == pytest.approx(float(ra[1][key]), rel=1e-4), key
    ck = torch.load(b / 'checkpoint.pt', weights_only=True)
    assert ck['epoch'] == 1 and ck['step'] == int(ra[1]['step'])


def test_device_cuda_without_a_gpu_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    import torch

    from assist_lab.cmvae_train import main
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: False)
    run = tmp_path / 'run'
    with pytest.raises(SystemExit) as exit_:
        main(['--data-dir', str(tmp_path / 'none'), '--run-dir', str(run), '--device', 'cuda'])
    assert exit_.value.code == 2 and 'no CUDA GPU' in capsys.readouterr().err
    assert not run.exists()
