"""docs/nodes.md holds every node's parameter table as the code declares it (docs/gen_nodes.py)."""
import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location('gen_nodes', Path(__file__).parents[1] / 'docs' / 'gen_nodes.py')
gen_nodes = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gen_nodes)


def test_node_parameter_tables_are_in_sync_with_the_code():
    assert gen_nodes.main(['--check']) == 0, 'docs/nodes.md is stale: run python docs/gen_nodes.py'
    text = gen_nodes.OUT.read_text(encoding='utf-8')
    for exe, module in gen_nodes.nodes().items():
        params = importlib.import_module(module).PARAMS
        assert f'## {exe}' in text and all(f'| `{name}` |' in text for name in params), exe


def test_readme_parameter_summaries_name_real_parameters():
    """Hand-written parameter summaries in the package READMEs name parameters the nodes declare (a `prefix_*`
    row names at least one), with the declared default where the row gives one value for one parameter."""
    import re
    from pathlib import Path

    from assist_policy.policy_node import PARAMS
    readme = (Path(__file__).resolve().parents[1] / 'ros2_ws/src/assist_policy/README.md').read_text()
    table = readme[readme.index('| parameter | default | meaning |'):]
    table = table[:table.index('\n\n')]
    rows = [ln for ln in table.splitlines()[2:] if ln.startswith('|')]
    assert len(rows) >= 10
    for row in rows:
        cells = [c.strip() for c in row.strip('|').split('|')]
        names = re.findall(r'`([a-z_*]+)`', cells[0])
        assert names, row
        for name in names:
            if name.endswith('*'):
                assert any(p.startswith(name[:-1]) for p in PARAMS), (name, row)
            else:
                assert name in PARAMS, (name, row)
        if len(names) == 1 and not names[0].endswith('*'):
            default = cells[1].split(' ')[0].strip("'")
            declared = PARAMS[names[0]].default
            shown = '' if declared == '' else str(declared).lower()
            assert default.lower() in (shown, f'{shown}'.rstrip('0').rstrip('.')), (names[0], default, declared)
