"""`make bench`: run every bench_*.py section and print one table."""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
import time
from pathlib import Path


def _fmt(value) -> str:
    if isinstance(value, float):
        return f'{value:,.3g}' if abs(value) < 100 else f'{value:,.0f}'
    return str(value)


def main(argv: list[str] | None = None) -> int:
    """Run the selected sections (default: all) and print name/value/unit/target rows."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('sections', nargs='*', help='section names, e.g. sim bridge (default: all)')
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    here = Path(__file__).parent
    names = sorted(m.name for m in pkgutil.iter_modules([str(here)]) if m.name.startswith('bench_'))
    if args.sections:
        names = [n for n in names if n.removeprefix('bench_') in args.sections]
    rows, failed = [], []
    for name in names:
        t0 = time.monotonic()
        try:
            mod = importlib.import_module(f'bench.{name}')
            section = mod.run()
        except Exception as exc:  # noqa: BLE001 - report the failing section, keep the others
            failed.append((name, repr(exc)))
            continue
        for row in section:
            rows.append((name.removeprefix('bench_'), row['name'], _fmt(row['value']), row.get('unit', ''),
                         str(row.get('target', ''))))
        print(f'# {name}: {time.monotonic() - t0:.1f} s', file=sys.stderr)
    header = ('section', 'metric', 'value', 'unit', 'target')
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(5)]
    line = '  '.join(h.ljust(w) for h, w in zip(header, widths))
    print(line)
    print('-' * len(line))
    for r in rows:
        print('  '.join(c.ljust(w) for c, w in zip(r, widths)))
    for name, err in failed:
        print(f'FAILED {name}: {err}')
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
