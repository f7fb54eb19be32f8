"""`make demo` (assist_lab.demo) on a tiny budget: the shipped assistants fly and the table is printed."""
import csv

from assist_lab.demo import available_assistants, main


def test_demo_flies_every_shipped_assistant_and_prints_the_table(tmp_path, capsys):
    out = tmp_path / 'demo'
    assert main(['--landings', '1', '--betas', '0.5', '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    assert available_assistants() == ['latent', 'oracle']          # the models the repository ships
    rows = list(csv.DictReader(open(out / 'landings.csv')))
    conditions = {r['condition'] for r in rows}
    assert len(rows) == 3 and {'unassisted', 'oracle+guard'} <= conditions
    assert any(c.startswith('latent+guard') for c in conditions)
    for cond in conditions:
        assert cond in printed
    assert (out / 'error_vs_beta.png').stat().st_size > 10_000
