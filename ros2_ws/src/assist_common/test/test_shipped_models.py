"""assist_common.shipped: $ASSIST_MODELS_DIR, then the ament index's share/<pkg>/models, then the checkout."""
from pathlib import Path

from assist_common.shipped import shipped_model_path

REPO_MODELS = Path(__file__).resolve().parents[4] / 'models'


def _fake_prefix(root: Path, package: str, files: list[str]) -> Path:
    """An install prefix with `package` in the ament index and `files` in its share/models."""
    (root / 'share' / 'ament_index' / 'resource_index' / 'packages').mkdir(parents=True)
    (root / 'share' / 'ament_index' / 'resource_index' / 'packages' / package).write_text('')
    models = root / 'share' / package / 'models'
    models.mkdir(parents=True)
    for name in files:
        (models / name).write_bytes(b'x')
    return root


def test_checkout_models_without_an_ament_index(monkeypatch):
    monkeypatch.delenv('ASSIST_MODELS_DIR', raising=False)
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    assert shipped_model_path('assist_policy', 'td3_latent_actor.pt') == REPO_MODELS / 'td3_latent_actor.pt'
    assert shipped_model_path('assist_perception', 'cmvae.pt') == REPO_MODELS / 'cmvae.pt'


def test_installed_share_wins_over_the_checkout(monkeypatch, tmp_path):
    prefix = _fake_prefix(tmp_path / 'install', 'assist_policy', ['td3_latent_actor.pt'])
    monkeypatch.delenv('ASSIST_MODELS_DIR', raising=False)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    got = shipped_model_path('assist_policy', 'td3_latent_actor.pt')
    assert got == prefix / 'share' / 'assist_policy' / 'models' / 'td3_latent_actor.pt'
    # a file the share lacks comes from the checkout
    assert shipped_model_path('assist_policy', 'td3_oracle_actor.pt') == REPO_MODELS / 'td3_oracle_actor.pt'


def test_a_file_found_nowhere_is_reported_where_the_install_expects_it(monkeypatch, tmp_path):
    prefix = _fake_prefix(tmp_path / 'install', 'assist_policy', [])
    monkeypatch.delenv('ASSIST_MODELS_DIR', raising=False)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    got = shipped_model_path('assist_policy', 'no_such_actor.pt')
    assert got == prefix / 'share' / 'assist_policy' / 'models' / 'no_such_actor.pt' and not got.exists()


def test_environment_override(monkeypatch, tmp_path):
    prefix = _fake_prefix(tmp_path / 'install', 'assist_perception', ['cmvae.pt'])
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    monkeypatch.setenv('ASSIST_MODELS_DIR', str(tmp_path / 'mine'))
    assert shipped_model_path('assist_perception', 'cmvae.pt') == tmp_path / 'mine' / 'cmvae.pt'
