"""The rule registry (assist_policy.rules): one entry per rule, one meaning of settings left out, refusals."""
from __future__ import annotations

import dataclasses

import pytest

from assist_policy import assistant as assistant_module, policy_node, rules
from assist_policy.assistant import Assistant, AssistantConfig, rules_off
from assist_policy.override import OverrideConfig
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.recall import RecallConfig
from assist_policy.rules import RULES, Rule, all_settings, changed, rule, settings, switched
from assist_policy.safety import SafetyConfig
from assist_policy.testing import constant_actor


def test_each_rule_has_one_entry_that_every_name_finds():
    assert [r.switch for r in RULES] == ['floor_guard', 'pilot_override', 'pad_recall', 'oscillation_damper']
    for r in RULES:
        assert rule(r.field) is rule(r.switch) is rule(r.flag) is r
    with pytest.raises(ValueError, match="no rule 'wall' \\(rules: floor_guard, pilot_override"):
        rule('wall')
    # the settings fields, the node's switches and its stage keys are the registry's
    assert {r.field for r in RULES} <= {f.name for f in dataclasses.fields(AssistantConfig)}
    assert {r.field for r in RULES} <= {f.name for f in dataclasses.fields(PolicyCoreConfig)}
    assert {r.switch for r in RULES} <= set(policy_node.PARAMS) and policy_node.RULE_SWITCHES == tuple(
        r.switch for r in RULES)
    assert {s.key for s in Assistant().stages} == {r.switch for r in RULES} | {'wall_guard'}


def test_a_rule_registered_twice_or_without_a_switch_is_refused(monkeypatch):
    twice = RULES + (Rule('guard2', 'floor_guard', 'guard2', SafetyConfig, False, 'guard', rules.safety.RULE.make),)
    with pytest.raises(TypeError, match="^rule switch 'floor_guard' registered twice$"):
        rules._check_registry(twice)

    @dataclasses.dataclass
    class NoSwitch:
        gain: float = 1.0
    with pytest.raises(TypeError, match='^rule extra: NoSwitch has no `enabled` field$'):
        rules._check_registry(RULES + (Rule('extra', 'extra', 'extra', NoSwitch, False, 'extra', None),))
    # a rule whose stage takes a key another stage has: refused when the chain is built
    clash = dataclasses.replace(rules.damper.RULE, make=lambda cfg, parts, threshold: (
        {}, (rules.recall.RecallStage(parts['recall']),)))
    monkeypatch.setattr(assistant_module, 'RULES', RULES[:-1] + (clash,))
    with pytest.raises(TypeError, match="^stage 'pad_recall' registered twice$"):
        Assistant()


def test_settings_left_out_are_the_defaults_everywhere(tmp_path):
    override = rule('override')
    assert settings(override) == OverrideConfig() and settings(override, None).enabled
    mine = OverrideConfig(persist_s=0.0)
    assert settings(override, mine) is mine
    assert settings(override, {'persist_s': 0.0}) == mine
    assert switched(override, False) == OverrideConfig(enabled=False)
    assert switched(override, True, {'persist_s': 0.0}) == mine
    # the node's core and the assistant read None as the defaults; off is `enabled` False
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]),
                      PolicyCoreConfig(mode='latent', override=None, recall=RecallConfig(enabled=False)))
    assert core.assistant.cfg.override == OverrideConfig() and core.assistant.override.cfg.enabled
    assert not core.assistant.recall.cfg.enabled
    assert all_settings(PolicyCoreConfig()) == {r.field: r.config() for r in RULES}
    assert all(not getattr(rules_off(), r.field).enabled for r in RULES)


def test_an_unknown_setting_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match=r"^pad_recall: unknown setting 'radius' \(known: .*enabled.*\)$"):
        settings(rule('recall'), {'radius': 1.0})
    with pytest.raises(ValueError, match=r"^floor_guard: unknown settings 'a', 'b' "):
        changed(rule('safety'), SafetyConfig(), {'b': 1, 'a': 2})
    with pytest.raises(TypeError, match='^oscillation_damper: settings must be None, a mapping or a DamperConfig'):
        settings(rule('damper'), SafetyConfig())
    # at run time: nothing changes
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]), PolicyCoreConfig(mode='latent'))
    before = dataclasses.asdict(core.assistant.cfg)
    with pytest.raises(ValueError, match="^pilot_override: unknown setting 'persist'"):
        core.configure(override={'persist': 0.0})
    assert dataclasses.asdict(core.assistant.cfg) == before
    core.configure(override={'persist_s': 0.0})
    assert core.override.cfg.persist_s == 0.0 and core.assistant.cfg.override is core.override.cfg


def test_goal_agnostic_rules_are_off_by_default_only_where_the_goal_is_known():
    assert [r.default_on('latent') for r in RULES] == [True] * 4
    assert [r.default_on('end_to_end') for r in RULES] == [True] * 4
    assert [r.default_on('oracle') for r in RULES] == [True, False, False, False]
    oracle = policy_node.params_for_mode('oracle')
    assert {r.switch: oracle[r.switch].default for r in RULES} == {
        'floor_guard': True, 'pilot_override': False, 'pad_recall': False, 'oscillation_damper': False}
    assert policy_node.params_for_mode('latent') == policy_node.PARAMS


def test_every_numeric_setting_declares_its_range_once_where_the_field_is():
    from assist_common.settings import RULE_KEY
    from assist_policy.flight import FlightConfig
    from assist_policy.settings import PARAM_KEY
    for cls in (*(r.config for r in RULES), FlightConfig, PolicyCoreConfig, AssistantConfig):
        for f in dataclasses.fields(cls):
            numeric = isinstance(f.default, (int, float)) and not isinstance(f.default, bool)
            if not numeric or f.name in ('ground_altitude_m',):          # any finite altitude
                continue
            assert RULE_KEY in f.metadata, f'{cls.__name__}.{f.name} declares no range'
            if PARAM_KEY in f.metadata:           # a node parameter: its range is the field's rule
                spec, r = f.metadata[PARAM_KEY], f.metadata[RULE_KEY]
                assert (r.gt if spec.min_exclusive else r.ge) == spec.min and r.le == spec.max, f.name
    with pytest.raises(ValueError, match=r'^SafetyConfig.window_m must be > 0, got 0.0$'):
        SafetyConfig(window_m=0.0)
    with pytest.raises(ValueError, match=r'^PolicyCoreConfig.pilot_timeout_s must be > 0, got 0.0$'):
        PolicyCoreConfig(pilot_timeout_s=0.0)
    with pytest.raises(ValueError, match=r"^PolicyCoreConfig.actor_velocity must be one of twist, odom, got 'body'$"):
        PolicyCoreConfig(actor_velocity='body')
    with pytest.raises(ValueError, match=r'^AssistantConfig.max_speed_mps must be >= 0.1, got 0.0$'):
        AssistantConfig(max_speed_mps=0.0)
    with pytest.raises(ValueError, match=r'^RecallConfig.vertical_fov_deg must be a finite number, got inf$'):
        RecallConfig(vertical_fov_deg=float('inf'))
