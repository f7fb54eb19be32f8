"""The one user cache root shared by the exported encoders and the generated textures."""
from __future__ import annotations

from assist_common import cache


def test_assist_cache_dir_names_the_root_of_every_kind(monkeypatch, tmp_path):
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'c'))
    assert cache.cache_dir('onnx') == tmp_path / 'c' / 'onnx'
    assert cache.scratch_dir('textures_v1') == tmp_path / 'c' / 'textures_v1'


def test_default_root_follows_an_absolute_xdg_cache_home_else_the_home_folder(monkeypatch, tmp_path):
    monkeypatch.delenv('ASSIST_CACHE_DIR', raising=False)
    monkeypatch.setenv('HOME', str(tmp_path / 'home'))
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'xdg'))
    assert cache.cache_root() == tmp_path / 'xdg' / 'assist'
    for ignored in ('', 'relative/cache'):          # the XDG specification ignores a relative value
        monkeypatch.setenv('XDG_CACHE_HOME', ignored)
        assert cache.cache_root() == tmp_path / 'home' / '.cache' / 'assist'


def test_off_turns_the_cache_off_and_files_a_library_must_read_go_to_a_scratch_folder(monkeypatch):
    for off in ('off', 'OFF'):
        monkeypatch.setenv('ASSIST_CACHE_DIR', off)
        assert cache.cache_root() is None and cache.cache_dir('onnx') is None
        scratch = cache.scratch_dir('textures_v1')
        assert scratch.is_absolute() and scratch.name == 'textures_v1' and 'off' not in scratch.parts
