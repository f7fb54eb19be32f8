"""Shipped parameter files match the nodes' declared parameters and valid core configs."""
from pathlib import Path

import pytest
import yaml

from assist_bridge.bridge_core import BridgeConfig
from assist_bridge.mavlink_bridge_node import PARAMS as BRIDGE_PARAMS
from assist_bridge.teleop_core import TeleopConfig
from assist_bridge.teleop_keyboard import PARAMS as TELEOP_PARAMS

CONFIG = Path(__file__).resolve().parents[1] / 'config'


def _params(name: str, node: str) -> dict:
    return yaml.safe_load((CONFIG / name).read_text())[node]['ros__parameters']


@pytest.mark.parametrize('name', ['bridge.yaml', 'bridge_real.yaml'])
def test_bridge_yaml_keys_are_declared_and_build_a_valid_config(name):
    p = _params(name, 'mavlink_bridge_node')
    assert set(p) <= set(BRIDGE_PARAMS), set(p) - set(BRIDGE_PARAMS)
    for k, v in p.items():
        assert type(v) is type(BRIDGE_PARAMS[k].default), f'{k}: {type(v)} vs declared default'
    cfg = BridgeConfig(**{k: v for k, v in p.items() if k in BridgeConfig.__dataclass_fields__})
    assert cfg.connection


def test_real_vehicle_file_halves_the_velocity():
    assert _params('bridge_real.yaml', 'mavlink_bridge_node')['velocity_scale'] == 0.5
    assert _params('bridge.yaml', 'mavlink_bridge_node')['velocity_scale'] == 1.0


def test_teleop_yaml():
    p = _params('teleop.yaml', 'teleop_keyboard')
    assert set(p) <= set(TELEOP_PARAMS)
    TeleopConfig(**{k: v for k, v in p.items() if k in TeleopConfig.__dataclass_fields__})
