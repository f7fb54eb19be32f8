"""Writes docs/results.md and the shipped actors' models/<actor>.metrics.json from the results files.

    python docs/gen_results.py            # after adding a run under docs/results/runs/ or editing the tables
    python docs/gen_results.py --check    # what the test suite runs (tests/test_docs_results.py): exit 1 if stale

Inputs: docs/results/template.md (the text, with `<!-- table: NAME -->` where each table goes),
docs/results/tables.yaml (the tables: which run and condition each cell summarises, or the recorded
figures of a run whose per-landing file was not kept) and docs/results/runs/<run>/landings.csv (evaluate's
and evaluate_graph's per-landing files, summarised with evaluate's own `summarize`).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
RESULTS = DOCS / 'results'
OUT = DOCS / 'results.md'
MARK = '<!-- table: {} -->'


class Runs:
    """landings.csv files of docs/results/runs, read once each."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._rows: dict[str, dict[str, list[dict]]] = {}

    def rows(self, run: str, condition: str) -> list[dict]:
        """The landings of `condition` in run `run` (KeyError with the reason when absent)."""
        from assist_lab.evaluate import read_landings
        if run not in self._rows:
            self._rows[run] = read_landings(self.root / run / 'landings.csv')
        if condition not in self._rows[run]:
            raise KeyError(f'{run}: no condition {condition!r} (has {sorted(self._rows[run])})')
        return self._rows[run][condition]

    def metrics(self, run: str, condition: str) -> dict:
        """n, mean, std, median, success, crash of one condition of a run (evaluate's summarize)."""
        from assist_lab.evaluate import summarize
        s = summarize(self.rows(run, condition))
        return {'n': s['n'], 'mean': s['error_mean'], 'std': s['error_std'], 'median': s['error_median'],
                'success': s['specified_success'], 'crash': s['crash_rate']}

    def same_outcome(self, a: str, b: str, condition: str) -> tuple[int, int]:
        """(landings with the same outcome in both runs, landings paired on beta and seed)."""
        left = {(r['beta'], r['seed']): r['outcome'] for r in self.rows(a, condition)}
        right = {(r['beta'], r['seed']): r['outcome'] for r in self.rows(b, condition)}
        paired = sorted(set(left) & set(right))
        return sum(left[k] == right[k] for k in paired), len(paired)

    def paired(self, a: tuple[str, str], b: tuple[str, str]) -> dict:
        """compare_landings' paired statistics of run/condition `b` against `a` (same beta and seed)."""
        from assist_lab.compare import paired_stats
        left = {(r['beta'], r['seed']): r for r in self.rows(*a)}
        right = {(r['beta'], r['seed']): r for r in self.rows(*b)}
        return paired_stats([(left[k], right[k]) for k in sorted(set(left) & set(right))])


def cell_metrics(cell, runs: Runs) -> dict | None:
    """The figures of a cell: computed from a run, or recorded; None for a text or same-outcome cell."""
    if isinstance(cell, dict) and 'run' in cell:
        return runs.metrics(cell['run'], cell['condition'])
    if isinstance(cell, dict) and 'mean' in cell:
        return cell
    return None


def _pct(x: float, digits: int) -> str:
    return f'{100 * x:.{digits}f} %'


def format_cell(cell, style: str, runs: Runs, bold: bool) -> list[str]:
    """Markdown text of one cell (the paper style spreads figures over four columns)."""
    if isinstance(cell, dict) and 'same_outcome' in cell:
        same, n = runs.same_outcome(*cell['same_outcome'], cell['condition'])
        return [f'{same} / {n}']
    if isinstance(cell, dict) and 'paired' in cell:      # b against a: [[run, condition], [run, condition]]
        s = runs.paired(*(tuple(side) for side in cell['paired']))
        key = cell['measure']
        if key == 'wrong_pad':
            return [f"{s['wrong_pad_a']} -> {s['wrong_pad_b']}"]
        e = s[key]
        return [f"{e['a']:.1f} -> {e['b']:.1f} ({100 * e['change']:+.1f} %, p {e['wilcoxon_p']:.2g})"]
    m = cell_metrics(cell, runs)
    if m is None:
        return [str(cell)]
    wrap = (lambda s: f'**{s}**') if bold else (lambda s: s)
    spread = f"{m['mean']:.3f} +- {m['std']:.3f}" if 'std' in m else f"{m['mean']:.3f}"
    if style == 'paper':
        return [wrap(spread), wrap(f"{m['median']:.3f}"), wrap(_pct(m['success'], 1)), wrap(_pct(m['crash'], 1))]
    if style == 'graph':
        return [f"{spread} ({m['median']:.3f}) / {_pct(m['success'], 0)} / {_pct(m['crash'], 0)}"]
    median = f" ({m['median']:.3f})" if 'median' in m else ''
    return [wrap(f"{m['mean']:.3f}{median} / {_pct(m['success'], 1)} / {_pct(m['crash'], 1)}")]


def render_table(table: dict, runs: Runs) -> str:
    """One Markdown table, with a note under it when its figures were recorded rather than computed."""
    lines = ['| ' + ' | '.join(table['header']) + ' |', '| ' + ' | '.join('---' for _ in table['header']) + ' |']
    for row in table['rows']:
        cells = [row['label']]
        last = len(row['cells']) - 1
        for k, cell in enumerate(row['cells']):
            bold = row.get('bold', False) or (row.get('bold_last', False) and k == last)
            cells += format_cell(cell, table['style'], runs, bold)
        lines.append('| ' + ' | '.join(cells) + ' |')
    if table.get('recorded'):
        computed = any(isinstance(cell, dict) and 'run' in cell for row in table['rows'] for cell in row['cells'])
        which = ('Rows without a per-landing file in docs/results/runs: figures' if computed else 'Figures')
        lines += ['', f"({which} as measured and recorded in [{Path(table['recorded']).name}]"
                      f"({Path(table['recorded']).relative_to('docs')}); the per-landing files were not kept: the "
                      'command below re-runs the measurement.)']
    return '\n'.join(lines)


def render(tables: dict, runs: Runs) -> str:
    """The whole of docs/results.md."""
    text = (RESULTS / 'template.md').read_text(encoding='utf-8')
    for name, table in tables.items():
        if name == 'models':
            continue
        if MARK.format(name) not in text:
            raise KeyError(f'docs/results/template.md has no {MARK.format(name)}')
        text = text.replace(MARK.format(name), render_table(table, runs))
    head = ('<!-- Generated by `python docs/gen_results.py` from docs/results/ (template.md, tables.yaml, '
            'runs/); edit those, not this file. -->\n')
    return head + text


def model_metrics(tables: dict, runs: Runs) -> dict[str, dict]:
    """models/<actor>.metrics.json contents: the rows of the tables that measured each shipped actor."""
    out = {}
    for model, entries in tables.get('models', {}).items():
        evaluations = []
        for e in entries:
            table = tables[e['table']]
            cell = table['rows'][e['row']]['cells'][e['cell']]
            m = cell_metrics(cell, runs)
            if m is None:
                raise ValueError(f"{model}: {e['table']} row {e['row']} cell {e['cell']} holds no figures")
            source = (f"docs/results/runs/{cell['run']}/landings.csv, condition {cell['condition']}"
                      if 'run' in cell else f"recorded in {table['recorded']}")
            evaluations.append({'what': e['what'], 'landings': m['n'],
                                **{k: round(float(m[k]), 4) for k in ('mean', 'std', 'median', 'success', 'crash')
                                   if k in m},
                                'source': source})
        out[model] = {'model': f'models/{model}.pt', 'metrics': 'error_m (mean, std, median: horizontal '
                      'distance from the goal pad centre, m), success (all legs on the goal pad), crash',
                      'evaluations': evaluations, 'tables': 'docs/results.md'}
    return out


def outputs() -> dict[Path, str]:
    """Every file this script writes, with its content."""
    tables = yaml.safe_load((RESULTS / 'tables.yaml').read_text(encoding='utf-8'))
    runs = Runs(RESULTS / 'runs')
    files = {OUT: render(tables, runs)}
    for model, metrics in model_metrics(tables, runs).items():
        files[REPO / 'models' / f'{model}.metrics.json'] = json.dumps(metrics, indent=2) + '\n'
    return files


def main(argv: list[str] | None = None) -> int:
    """Write the files, or with --check report the stale ones and exit 1."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--check', action='store_true', help='exit 1 if a generated file differs; write nothing')
    args = ap.parse_args(argv)
    stale = []
    for path, text in outputs().items():
        old = path.read_text(encoding='utf-8') if path.exists() else None
        if old != text:
            stale.append(path.relative_to(REPO))
            if not args.check:
                path.write_text(text, encoding='utf-8')
    if args.check and stale:
        sys.stderr.write(f'stale: {", ".join(map(str, stale))}: run python docs/gen_results.py\n')
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
