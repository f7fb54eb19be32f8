"""Private DDS domains for graphs a program starts on this machine (tests, evaluate_graph): standard library only.

A private graph runs on its own ROS_DOMAIN_ID so it never meets anyone else's nodes. The domains drawn come from
``$ASSIST_DOMAIN_IDS`` ('lo-hi', inclusive; default 100-199), so runs side by side that are given disjoint ranges
(the test suite's parallel workers, see conftest.py) never draw the same one.
"""
from __future__ import annotations

import os
import random

DOMAIN_IDS_ENV = 'ASSIST_DOMAIN_IDS'
DEFAULT_DOMAIN_IDS = (100, 199)
MAX_DOMAIN_ID = 232          # higher ones overflow Fast DDS's default UDP ports


def domain_range() -> tuple[int, int]:
    """(lo, hi) of $ASSIST_DOMAIN_IDS, inclusive (ValueError, one line, for a malformed or out-of-range value)."""
    text = os.environ.get(DOMAIN_IDS_ENV, '').strip()
    if not text:
        return DEFAULT_DOMAIN_IDS
    try:
        lo, hi = (int(part) for part in text.split('-'))
    except ValueError:
        raise ValueError(f"${DOMAIN_IDS_ENV} {text!r}: expected 'lo-hi', e.g. 100-149") from None
    if not 1 <= lo <= hi <= MAX_DOMAIN_ID:
        raise ValueError(f'${DOMAIN_IDS_ENV} {text!r}: expected 1 <= lo <= hi <= {MAX_DOMAIN_ID}')
    return lo, hi


def private_domain_ids(count: int = 1, rng: random.Random | None = None) -> list[int]:
    """`count` different domains drawn from domain_range() (a fresh generator unless `rng` is given)."""
    lo, hi = domain_range()
    if count > hi - lo + 1:
        raise ValueError(f'{count} domains asked of {lo}-{hi}')
    rng = rng or random.Random(os.getpid() ^ int.from_bytes(os.urandom(8), 'little'))
    return rng.sample(range(lo, hi + 1), count)


def private_domain_id(rng: random.Random | None = None) -> int:
    """One domain drawn from domain_range()."""
    return private_domain_ids(1, rng)[0]


def split_range(worker: int, workers: int) -> str:
    """The 'lo-hi' slice of the default range for worker `worker` of `workers` (disjoint slices)."""
    lo, hi = DEFAULT_DOMAIN_IDS
    span = (hi - lo + 1) // workers
    if span < 1 or not 0 <= worker < workers:
        raise ValueError(f'worker {worker} of {workers}: no slice of {lo}-{hi}')
    return f'{lo + worker * span}-{lo + (worker + 1) * span - 1}'
