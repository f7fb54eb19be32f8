"""compare_landings: two evaluate runs of the same landings, landing by landing (old vs new, same seeds).

evaluate writes one row per landing (condition, beta, seed, outcome, error, pilot...). Two runs of the
same landings (same --pilot, --seed, --betas, --landings; e.g. the shipped assistant before and after a
change, or two actors) are paired on (beta, seed). The report: each side's error mean (median) /
goal-pad success / crash, the paired error difference with its standard error and a Wilcoxon
signed-rank test, success and crash flips with an exact McNemar test (binomial on the discordant
pairs), the time to land and path length of both (mean, relative change, Wilcoxon) and the wrong-pad
landings (McNemar), the same per pilot family when the rows name one, and every landing whose outcome changed or
whose error moved more than --worse-m. ``--out`` writes the pairs as CSV, ``--plot`` draws them (errors
A against B, the paired difference's distribution).

    compare_landings --a runs/old/m7 runs/old/m99 --b runs/new/m7 runs/new/m99
    compare_landings --a runs/ev/landings.csv --condition-a unassisted --b runs/ev/landings.csv \\
        --condition-b latent+guard+override+recall+damper
"""
from __future__ import annotations

import argparse
import csv
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from assist_common.atomic import atomic_path

from .evaluate import mean_se, read_landings

log = logging.getLogger(__name__)
PAIR_FIELDS = ('beta', 'seed', 'pilot', 'outcome_a', 'outcome_b', 'error_a', 'error_b', 'delta_error',
               'duration_a', 'duration_b', 'path_a', 'path_b')


@dataclass
class Side:
    """One side of the comparison: landing rows keyed by (beta, seed), and the condition they came from."""

    rows: dict[tuple[float, int | None], dict]
    condition: str


def load_side(paths: list[str], condition: str | None) -> Side:
    """Rows of `condition` from landings.csv files (or folders holding one); ValueError when ambiguous or absent."""
    rows: dict[tuple[float, int | None], dict] = {}
    chosen = condition
    for p in paths:
        path = Path(p)
        if path.is_dir():
            path = path / 'landings.csv'
        if not path.is_file():
            raise ValueError(f'{p}: no landings.csv there')
        by_cond = read_landings(path)
        if chosen is None:
            assisted = [c for c in by_cond if c != 'unassisted']
            if len(assisted) != 1:
                raise ValueError(f'{path}: conditions {sorted(by_cond)}; name one with --condition-a/-b')
            chosen = assisted[0]
        if chosen not in by_cond:
            raise ValueError(f'{path}: no condition {chosen!r} (has {sorted(by_cond)})')
        for r in by_cond[chosen]:
            key = (float(r['beta']), r.get('seed'))
            if key in rows:
                raise ValueError(f'{path}: landing beta {key[0]} seed {key[1]} appears twice on one side')
            rows[key] = r
    if chosen is None:
        raise ValueError('no landings.csv given')
    return Side(rows, chosen)


def _fmt(rows: list[dict]) -> str:
    """error mean (median) / success / crash of `rows`."""
    e = np.array([r['error_m'] for r in rows], dtype=float)
    return (f'{e.mean():.3f} ({np.median(e):.3f}) m / {100 * np.mean([r["success"] for r in rows]):.1f} % / '
            f'{100 * np.mean([r["crash"] for r in rows]):.1f} %')


def paired_stats(pairs: list[tuple[dict, dict]]) -> dict:
    """Paired statistics of (a, b) landing rows: error difference b - a, success and crash flips, tests."""
    d = np.array([b['error_m'] - a['error_m'] for a, b in pairs], dtype=float)
    delta, se = mean_se(d)
    out = {'n': len(d), 'delta_error': delta, 'delta_se': se}
    nonzero = d[np.abs(d) > 1e-9]
    out['wilcoxon_p'] = float(stats.wilcoxon(nonzero).pvalue) if len(nonzero) >= 1 else 1.0
    flags = {'success': lambda r: bool(r['success']), 'crash': lambda r: bool(r['crash']),
             'wrong_pad': lambda r: r['outcome'] == 'wrong_pad'}
    for key, flag in flags.items():
        gained = sum(1 for a, b in pairs if flag(b) and not flag(a))
        lost = sum(1 for a, b in pairs if flag(a) and not flag(b))
        out[f'{key}_gained'], out[f'{key}_lost'] = gained, lost
        out[f'{key}_a'], out[f'{key}_b'] = sum(flag(a) for a, _ in pairs), sum(flag(b) for _, b in pairs)
        out[f'{key}_mcnemar_p'] = (float(stats.binomtest(gained, gained + lost, 0.5).pvalue)
                                   if gained + lost else 1.0)
    for key in EFFORT:
        both = [(float(a.get(key, 'nan')), float(b.get(key, 'nan'))) for a, b in pairs]
        both = np.array([x for x in both if np.isfinite(x[0]) and np.isfinite(x[1])], dtype=float).reshape(-1, 2)
        if len(both) == 0:
            continue
        diff = both[:, 1] - both[:, 0]
        nz = diff[np.abs(diff) > 1e-9]
        out[key] = {'n': len(both), 'a': float(both[:, 0].mean()), 'b': float(both[:, 1].mean()),
                    'change': float(both[:, 1].mean() / both[:, 0].mean() - 1.0) if both[:, 0].mean() else 0.0,
                    'wilcoxon_p': float(stats.wilcoxon(nz).pvalue) if len(nz) >= 1 else 1.0}
    return out


# per-landing effort columns compared pair by pair where both sides have them (older tables lack path_m)
EFFORT = {'duration_s': 'time to land (s)', 'path_m': 'path length (m)'}


def changed(pairs: list[tuple[dict, dict]], worse_m: float) -> list[tuple[dict, dict]]:
    """The pairs whose outcome differs or whose error moved more than `worse_m`."""
    return [(a, b) for a, b in pairs
            if a['outcome'] != b['outcome'] or abs(b['error_m'] - a['error_m']) > worse_m]


def report(a: Side, b: Side, worse_m: float = 0.25) -> tuple[str, list[tuple[dict, dict]]]:
    """Text report of B against A on their common landings, and the pairs (in beta, seed order)."""
    keys = sorted(set(a.rows) & set(b.rows), key=lambda k: (k[0], -1 if k[1] is None else k[1]))
    if not keys:
        raise ValueError('the two sides share no landing (same --pilot, --seed, --betas, --landings?)')
    pairs = [(a.rows[k], b.rows[k]) for k in keys]
    lines = [f'A: {a.condition}', f'B: {b.condition}', f'{len(pairs)} landings in both'
             + (f' ({len(a.rows) - len(pairs)} only in A, {len(b.rows) - len(pairs)} only in B)'
                if len(a.rows) != len(pairs) or len(b.rows) != len(pairs) else '')]
    groups = {'all': pairs}
    pilots = sorted({str(x.get('pilot') or '') for x, _ in pairs} - {''})
    if len(pilots) > 1:
        groups.update({p: [(x, y) for x, y in pairs if x.get('pilot') == p] for p in pilots})
    lines.append(f'{"landings":<18} {"n":>4}  {"A error mean (median) / success / crash":<40}  '
                 f'{"B":<40}  {"d error (+- se)":>17}  {"Wilcoxon p":>10}  {"success +/-":>11}  {"p":>6}  '
                 f'{"crash +/-":>9}')
    for name, ps in groups.items():
        s = paired_stats(ps)
        lines.append(f'{name:<18} {s["n"]:>4}  {_fmt([x for x, _ in ps]):<40}  {_fmt([y for _, y in ps]):<40}  '
                     f'{s["delta_error"]:>+8.3f} +- {s["delta_se"]:<5.3f}  {s["wilcoxon_p"]:>10.3g}  '
                     f'{s["success_gained"]:>5}/{s["success_lost"]:<5}  {s["success_mcnemar_p"]:>6.3g}  '
                     f'{s["crash_gained"]:>4}/{s["crash_lost"]:<4}')
    s = paired_stats(pairs)
    for key, label in EFFORT.items():
        if key in s:
            e = s[key]
            lines.append(f'{label:<18} {e["n"]:>4}  A {e["a"]:.2f}  B {e["b"]:.2f}  ({100 * e["change"]:+.1f} %)  '
                         f'Wilcoxon p {e["wilcoxon_p"]:.3g}')
    lines.append(f'{"wrong pad":<18} {s["n"]:>4}  A {s["wrong_pad_a"]}  B {s["wrong_pad_b"]}  '
                 f'(+{s["wrong_pad_gained"]}/-{s["wrong_pad_lost"]}, McNemar p {s["wrong_pad_mcnemar_p"]:.3g})')
    moved = changed(pairs, worse_m)
    lines.append(f'changed (outcome, or error moved > {worse_m:g} m): {len(moved)}')
    for x, y in moved:
        lines.append(f'  beta {x["beta"]:<5g} seed {x.get("seed")!s:<6} {str(x.get("pilot") or ""):<16} '
                     f'{x["outcome"]} {x["error_m"]:.3f} -> {y["outcome"]} {y["error_m"]:.3f}')
    return '\n'.join(lines), pairs


def write_pairs(path: Path, pairs: list[tuple[dict, dict]]) -> None:
    """The pairs as CSV (PAIR_FIELDS), written in one atomic step as evaluate writes its tables."""
    with atomic_path(path) as tmp, open(tmp, 'w', newline='', encoding='utf-8') as fh:
        w = csv.writer(fh)
        w.writerow(PAIR_FIELDS)
        for a, b in pairs:
            w.writerow([a['beta'], a.get('seed'), a.get('pilot') or '', a['outcome'], b['outcome'], a['error_m'],
                        b['error_m'], round(b['error_m'] - a['error_m'], 4), a.get('duration_s', ''),
                        b.get('duration_s', ''), a.get('path_m', ''), b.get('path_m', '')])


def plot_pairs(path: Path, pairs: list[tuple[dict, dict]], a: str, b: str) -> None:
    """The paired comparison as a figure: each landing's error in A against B (goal-pad success marked per
    side), and the distribution of the paired difference B - A."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    ea = np.array([x['error_m'] for x, _ in pairs])
    eb = np.array([y['error_m'] for _, y in pairs])
    kind = np.array([2 * bool(x['success']) + bool(y['success']) for x, y in pairs])
    fig, (ax, hx) = plt.subplots(1, 2, figsize=(10.0, 4.4))
    for k, (label, colour) in enumerate((('neither on the goal pad', 'tab:gray'), ('B only', 'tab:green'),
                                         ('A only', 'tab:red'), ('both', 'tab:blue'))):
        m = kind == k
        if m.any():
            ax.scatter(ea[m], eb[m], s=12, alpha=0.7, color=colour, label=f'{label} ({int(m.sum())})')
    top = max(float(ea.max()), float(eb.max()), 0.1) * 1.05
    ax.plot([0, top], [0, top], color='k', lw=0.8, ls='--')
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_xlabel(f'A error (m): {a}', fontsize=8)
    ax.set_ylabel(f'B error (m): {b}', fontsize=8)
    ax.legend(fontsize=7, title='goal-pad success', title_fontsize=7)
    ax.grid(alpha=0.3)
    d = eb - ea
    hx.hist(d, bins=min(40, max(5, len(d) // 4)), color='tab:purple', alpha=0.8)
    hx.axvline(0.0, color='k', lw=0.8)
    hx.axvline(float(np.median(d)), color='tab:orange', lw=1.2, label=f'median {np.median(d):+.3f} m')
    hx.set_xlabel('paired error difference B - A (m)')
    hx.set_ylabel('landings')
    hx.legend(fontsize=8)
    hx.grid(alpha=0.3)
    fig.suptitle(f'{len(pairs)} landings flown by both', fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format='png')
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Console entry point: compare_landings --a ... --b ... (exit 2 with one line on bad input)."""
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    ap = argparse.ArgumentParser(prog='compare_landings', description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--a', nargs='+', required=True, help='landings.csv files or run folders: the baseline')
    ap.add_argument('--b', nargs='+', required=True, help='landings.csv files or run folders: the change')
    ap.add_argument('--condition-a', default=None, help='condition of A (default: its only assisted one)')
    ap.add_argument('--condition-b', default=None, help='condition of B (default: its only assisted one)')
    ap.add_argument('--worse-m', type=float, default=0.25, help='list landings whose error moved more than this')
    ap.add_argument('--out', default='', help='write the pairs to this CSV')
    ap.add_argument('--plot', default='', help='draw the paired comparison into this PNG')
    args = ap.parse_args(argv)
    try:
        a, b = load_side(args.a, args.condition_a), load_side(args.b, args.condition_b)
        text, pairs = report(a, b, args.worse_m)
    except (OSError, ValueError) as exc:
        print(f'compare_landings: {exc}', file=sys.stderr)
        return 2
    print(text)
    if args.out:
        write_pairs(Path(args.out), pairs)
        log.info('pairs written to %s', args.out)
    if args.plot:
        plot_pairs(Path(args.plot), pairs, a.condition, b.condition)
        log.info('figure written to %s', args.plot)
    return 0


if __name__ == '__main__':
    sys.exit(main())
