"""docs/nodes.md holds every node's parameter table as the code declares it (docs/gen_nodes.py)."""
import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location('gen_nodes', Path(__file__).parents[1] / 'docs' / 'gen_nodes.py')
gen_nodes = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(gen_nodes)


def test_node_parameter_tables_are_in_sync_with_the_code():
    assert gen_nodes.main(['--check']) == 0, 'docs/nodes.md is stale: run python docs/gen_nodes.py'
    text = gen_nodes.OUT.read_text(encoding='utf-8')
    for exe, module in gen_nodes.NODES.items():
        params = importlib.import_module(module).PARAMS
        assert f'## {exe}' in text and all(f'| `{name}` |' in text for name in params), exe
