"""Every policy variant the benchmark knows: policies.py's (the scripted expert and its degraded
variants, `wrong-<d>cm`) and families.py's (behaviour cloning, other scripted controllers, partial
outcomes, wandering hands), by name.

`make_policy(task, variant, seed)` builds one for an episode, `check_variants(tasks, variants)`
says what is wrong with a list of names (naming the known names of both modules), `run_episode`
runs one in the simulator with policies.run and `measure_truth` runs it over seeds. This module
sits above both: policies.py knows only its own variants, families.py builds on policies.py and
neither imports this one. Imports numpy only (a cloned network is trained with torch).
"""

from __future__ import annotations

import families
import policies
from policies import Episode


def check(task: str, variant: str) -> None:
    """Raises ValueError naming the known names of policies.py and families.py for `task` unless
    `variant` is defined for it."""
    if families.family_of(variant):
        families.check(task, variant)
        return
    try:
        policies.variant_params(task, variant)
    except ValueError:
        if task not in policies.VARIANT_PARAMS:
            raise
        raise ValueError(f"unknown variant {variant!r} for {task} (known: {', '.join(policies.known(task))}; "
                         f"families: {', '.join(families.variants(tasks=[task]))})") from None


def check_variants(tasks: list[str], variants: list[str]) -> str | None:
    """None when every variant is defined for every task, else what is wrong, in one line."""
    for v in variants:
        for t in tasks:
            try:
                check(t, v)
            except ValueError as e:
                return str(e)
    return None


def make_policy(task: str, variant: str, seed: int):
    """A variant's policy for one episode: act(image, state, n) -> float32[n, 4]."""
    check(task, variant)
    return families.make_policy(task, variant, seed) if families.family_of(variant) else policies.Policy(task, variant, seed)


def run_episode(task: str, variant: str, seed: int, horizon: int = 120, chunk: int = 24, resolution: int = 64,
                record: bool = False) -> Episode:
    """One episode of the variant's policy in the simulator from the placement of `seed`, as the
    world-model evaluator runs it (policies.run: a frame every `chunk` steps, `chunk` commands
    back). Without `record` it stops at the first success; with it the episode runs the whole
    horizon and keeps every frame."""
    return policies.run(make_policy(task, variant, seed), task, seed, horizon, chunk, resolution, record)


def measure_truth(task: str, variant: str, seeds, horizon: int = 120, chunk: int = 24, resolution: int = 64) -> list[Episode]:
    """Per seed, the episode in the simulator without its frames (run_episode)."""
    return [run_episode(task, variant, seed, horizon, chunk, resolution) for seed in seeds]
