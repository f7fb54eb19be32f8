"""`make demo` until the assistant lands: scripted landings in the sim core, results as a table."""
from __future__ import annotations

import argparse
import logging
import sys
import time

from .core.scripted import expert_command
from .core.world import LandingWorld


def main(argv: list[str] | None = None) -> int:
    """Fly N seeded landings with the scripted expert and print each landing and a summary."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--landings', type=int, default=5)
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    world = LandingWorld(seed=args.seed)
    print(f"{'episode':>7} {'goal':>4} {'landed':>6} {'outcome':>9} {'error_m':>8} {'sim_s':>6}")
    results = []
    t0 = time.perf_counter()
    for _ in range(args.landings):
        world.reset()
        while not world.done:
            world.step(expert_command(world.state.position, world.goal_position))
            world.render()
        r = world.result
        results.append(r)
        print(f'{r.episode:>7} {r.goal_index:>4} {str(r.landed_index):>6} {r.outcome:>9} {r.error_m:>8.3f} '
              f'{r.duration_s:>6.1f}')
    wall = time.perf_counter() - t0
    ok = sum(r.success for r in results)
    print(f'scripted expert: {ok}/{len(results)} successes, mean error '
          f'{sum(r.error_m for r in results) / len(results):.3f} m, '
          f'{sum(r.duration_s for r in results) / wall:.1f}x real time with the camera at 20 Hz')
    world.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
