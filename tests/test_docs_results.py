"""docs/results.md and models/<actor>.metrics.json are what docs/gen_results.py makes of docs/results/."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location('gen_results', REPO / 'docs' / 'gen_results.py')
gen_results = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gen_results)


def test_results_and_model_metrics_are_generated_from_the_results_files():
    assert gen_results.main(['--check']) == 0, 'stale: run python docs/gen_results.py'


def test_computed_cells_are_evaluates_own_summary():
    from assist_lab.evaluate import read_landings, summarize
    rows = read_landings(REPO / 'docs/results/runs/cmp_mix_graph/landings.csv')['latent+guard+override+recall+damper']
    s = summarize(rows)
    text = (REPO / 'docs' / 'results.md').read_text()
    assert f"{s['error_mean']:.3f} +- {s['error_std']:.3f} ({s['error_median']:.3f})" in text
    latent = json.loads((REPO / 'models' / 'td3_latent_actor.metrics.json').read_text())
    graph = [e for e in latent['evaluations'] if 'held-out mix through the node graph' in e['what']]
    assert graph and graph[0]['landings'] == len(rows) == 20 and graph[0]['mean'] == round(s['error_mean'], 4)


def test_every_shipped_model_has_metrics():
    for weights in sorted((REPO / 'models').glob('*.pt')):
        metrics = weights.with_suffix('.metrics.json')
        assert metrics.is_file(), f'{weights.name} has no {metrics.name}'
        assert json.loads(metrics.read_text()), metrics
