"""What one landing is made of, drawn from its seed: the one place the draw order is written.

``landing_plan(seed, beta, pilot_family, ...)`` returns the scene seed (``LandingWorld.reset(seed=scene_seed)``
builds the scene and picks the goal pad from it), the pilot (``make_pilot(pilot_family, alpha, beta, cfg,
np.random.default_rng(pilot_seed), pads=...)``; for a population such as ``mix`` the family is drawn from that
generator, ``pilot_family_resolved`` names it) and the depth-noise seed of the landing. LandingAssistEnv.reset
draws its landing through it, and the graph evaluation (assist_lab.graph_eval, which hands each landing's seeds to
sim_node and sim_pilot_node) flies the same landing from the same plan.

Draw order from the episode generator (``gymnasium``'s ``np_random`` seeded with `seed`):

1. ``integers(0, 2**31 - 1)``: the scene seed (drawn even when a scene seed is given: the env's
   ``options.get('scene_seed', rng.integers(...))`` evaluates its default first);
2. ``uniform(*beta_range)``: the pilot skill (likewise drawn even when `beta` is given);
3. ``uniform()``: only when no pilot was asked for by name and ``paper_share > 0`` (training): below it the
   landing is flown by the paper pilot;
4. ``integers(2**31)``: the seed of the pilot's own generator;
5. ``integers(2**31)``: the depth-noise seed (drawn last, so the scene and the pilot do not depend on it).

Pure numpy (no rclpy, no pybullet).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from assist_sim.pilots import resolve_pilot_name
from gymnasium.utils import seeding


@dataclass(frozen=True)
class LandingPlan:
    """The seeds and settings of one landing (see the module docstring)."""

    scene_seed: int
    pilot_family: str            # as asked: a family or a population (make_pilot's name argument)
    pilot_family_resolved: str   # the family that flies (a population's draw)
    pilot_seed: int              # seed of the pilot's generator: np.random.default_rng(pilot_seed)
    noise_seed: int              # depth-noise seed of the landing
    beta: float
    alpha: float


def episode_rng(seed: int | None) -> np.random.Generator:
    """The episode generator gymnasium's Env.reset(seed=seed) gives env.np_random."""
    return seeding.np_random(seed)[0]


def landing_plan(seed: int | np.random.Generator | None, beta: float | None = None, pilot_family: str = 'paper',
                 alpha: float = 0.5, *, beta_range: tuple[float, float] = (0.0, 1.0), paper_share: float = 0.0,
                 scene_seed: int | None = None, pilot_named: bool = True) -> LandingPlan:
    """Draw one landing's plan from `seed` (or from a generator, advanced in place) in env.reset's order.

    `beta`/`scene_seed` None: drawn (the draw happens either way); `pilot_named` False means the pilot family
    came from the config, not from reset's options, so `paper_share` may replace it by the paper pilot.
    """
    rng = seed if isinstance(seed, np.random.Generator) else episode_rng(seed)
    drawn_scene = int(rng.integers(0, 2**31 - 1))
    drawn_beta = float(rng.uniform(*beta_range))
    family = str(pilot_family)
    if not pilot_named and paper_share > 0 and rng.uniform() < paper_share:
        family = 'paper'
    pilot_seed = int(rng.integers(2**31))
    noise_seed = int(rng.integers(2**31))
    resolved = resolve_pilot_name(family, np.random.default_rng(pilot_seed))
    return LandingPlan(scene_seed=drawn_scene if scene_seed is None else int(scene_seed), pilot_family=family,
                       pilot_family_resolved=resolved, pilot_seed=pilot_seed, noise_seed=noise_seed,
                       beta=drawn_beta if beta is None else float(beta), alpha=float(alpha))


def landing_seeds(seed: int, betas, landings: int) -> list[tuple[int, float]]:
    """(seed, beta) of every landing of an evaluation, in its order: landing k at beta index b has seed
    seed + 1000 b + k (so a run split by beta pairs with the whole run)."""
    return [(seed + 1000 * bi + k, float(beta)) for bi, beta in enumerate(betas) for k in range(landings)]


def evaluation_plans(seed: int, betas: tuple[float, ...], landings: int, pilot_family: str = 'paper',
                     alpha: float = 0.5) -> list[tuple[int, LandingPlan]]:
    """(seed, plan) of every landing `evaluate` flies, in its order (`landing_seeds`)."""
    return [(s, landing_plan(s, beta, pilot_family, alpha)) for s, beta in landing_seeds(seed, betas, landings)]
