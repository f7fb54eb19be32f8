"""A non-learned rule added in one place (its module and its line in assist_policy.rules.RULES) reaches every tool:
the assistant's chain, policy_node's parameters and /diagnostics, the env, evaluate's and evaluate_graph's options,
condition names and columns, and replay_assist's options.

The rule here is declared in a fresh interpreter, appended to RULES before anything else reads the registry, as its
line in rules.py would put it; nothing else is changed.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

PROGRAM = textwrap.dedent('''
    import dataclasses, json
    import numpy as np
    from assist_policy import rules
    from assist_policy.settings import node_param
    from assist_policy.stage import ACTION, Decision, Rule, Stage

    @dataclasses.dataclass
    class HushConfig:
        enabled: bool = node_param(True, 'hush', 'Hush (test rule): the actor action halved.')
        share: float = node_param(0.5, 'hush_share', 'Share of the action kept.', min=0.0, max=1.0)

    class HushStage(Stage):
        key, phase, position = 'hush', ACTION, 25          # after the override, before the recall

        def __init__(self, cfg):
            self.cfg = cfg

        def apply(self, ctx, d):
            if not self.cfg.enabled or d.final:
                return None
            return Decision(d.agent * self.cfg.share, None, self.key, 'hush: action scaled')

        def modes(self, acted, ran):
            return ('scaled',) if acted else ()

        def diagnostics(self, modes):
            return {'hush_scaled': modes['hush:scaled']}

    RULE = Rule('hush', 'hush', 'quiet', HushConfig, goal_agnostic=True, title='hush',
                make=lambda cfg, parts, threshold: ({'hush': cfg}, (HushStage(cfg),)))
    rules.RULES = rules.RULES + (RULE,)          # its line in the registry

    from assist_policy import settings
    from assist_policy.assistant import Assistant, AssistantConfig
    from assist_policy.policy_core import PolicyCoreConfig
    from assist_policy.policy_node import params_for_mode
    from assist_policy.stage import StepContext
    from assist_lab import evaluate, graph_eval
    from assist_lab.env import EnvConfig
    from assist_bags.replay import ReplayConfig, rules_on

    out = {}
    a = Assistant()
    out['stages'] = [s.key for s in a.stages]
    ctx = StepContext(0.0, np.zeros(3), np.zeros(3), np.array([0.0, 0.0, 5.0]), np.zeros(3), None, None,
                      (1.0, 1.0, 1.0))
    res = a.step(ctx, np.array([0.8, 0.0, 0.0]))
    out['step'] = [res.key, res.agent.tolist(), list(res.acted)]
    out['diagnostics'] = {k: v for k, v in a.diagnostics().items() if k.startswith('hush')}
    out['assistant_cfg'] = type(AssistantConfig().hush).__name__
    params = settings.parameters(PolicyCoreConfig)
    out['node_params'] = sorted(k for k in params if k.startswith('hush'))
    out['oracle_default'] = params_for_mode('oracle')['hush'].default
    out['latent_default'] = params_for_mode('latent')['hush'].default
    out['env_off'] = EnvConfig().hush.enabled
    out['eval_default'] = evaluate.EvalArgs().hush
    out['eval_help'] = evaluate.HELP['hush']
    out['eval_columns'] = [c for c in evaluate.LANDING_FIELDS if c.startswith('quiet')]
    out['eval_name'] = evaluate.condition_name('latent', evaluate.rules_flying(evaluate.EvalArgs(), 'latent'), False)
    out['graph_default'] = graph_eval.GraphEvalArgs().hush
    out['graph_counter'] = graph_eval.POLICY_COUNTERS.get('quiet_fraction')
    out['replay_default'] = ReplayConfig().hush
    out['replay_on'] = rules_on(ReplayConfig(hush='off'), '', [])
    print(json.dumps(out))
''')


def test_a_rule_declared_in_its_module_flies_and_is_named_by_every_tool():
    proc = subprocess.run([sys.executable, '-c', PROGRAM], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    # the chain: its stage where it says, acting on the actor's action, counted
    assert out['stages'] == ['oscillation_damper', 'pilot_override', 'hush', 'pad_recall', 'floor_guard',
                             'wall_guard']
    assert out['step'] == ['hush', [0.4, 0.0, 0.0], ['hush']]
    assert out['diagnostics'] == {'hush_engaged': 1, 'hush_scaled': 1}
    # its settings in every config, its node parameters, off by default where the goal is known
    assert out['assistant_cfg'] == 'HushConfig'
    assert out['node_params'] == ['hush', 'hush_share']
    assert out['oracle_default'] is False and out['latent_default'] is True
    assert out['env_off'] is False
    # evaluate / evaluate_graph / replay_assist options, names and columns
    assert out['eval_default'] is None and out['eval_help'].startswith('apply the hush (__main__)')
    assert out['eval_columns'] == ['quiet_fraction']
    assert out['eval_name'].endswith('+quiet')
    assert out['graph_default'] is None and out['graph_counter'] == 'hush_engaged'
    assert out['replay_default'] == 'auto'
    assert out['replay_on'] == {'safety': True, 'override': True, 'recall': True, 'damper': True, 'hush': False}
