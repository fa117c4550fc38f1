"""Which experiments of ``svrobs reproduce`` run together, and what each one costs.

The groups around the largest grid (docs/performance.md#one-pass): an experiment
whose records are a selection of another's takes them from that run (a child), one
that differs only in the bounds method shares its data (a variant).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from svrobs_core import parse_spec
from svrobs_core.pipeline import shares_data
from svrobs_core.wishart_draws import dataset_draws


class ReproduceError(Exception):
    """A stage of an experiment failed: the reproduction is not complete."""


def derivable(child: dict, parent: dict) -> bool:
    """True when every record of ``child`` is a record of ``parent`` (same keys),
    up to ``mc_reps``: the parent's run then computes the Monte Carlo J as far
    as the child needs it and writes each spec's own records
    (``UnitResult.with_mc_reps``)."""
    c, p = parse_spec(child), parse_spec(parent)
    cd, pd = c.to_dict(), p.to_dict()
    for k in cd.keys() | pd.keys():  # both ways: e.g. bounds_method is in only one of them
        if k in ("systems", "gamma", "estimators", "mc_reps"):
            continue
        if cd.get(k) != pd.get(k):
            return False
    # the seed key holds the system index: it must be the same in both
    for i, s in enumerate(cd["systems"]):
        if i >= len(pd["systems"]) or pd["systems"][i] != s:
            return False
    if not set(c.estimators) <= set(p.estimators):
        return False
    if "cost" in c.stages:  # the cost ratio couples the gammas of a repetition
        return c.gamma == p.gamma
    return set(c.gamma) <= set(p.gamma)


@dataclass
class Group:
    """One pass: ``parent``'s units; ``variants`` share its data (other bounds
    methods, computed in the same pass); ``children`` take their records from it."""

    parent: str
    variants: list[str] = field(default_factory=list)
    children: list[str] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return [self.parent, *self.variants, *self.children]


def plan(specs: dict[str, dict], derive: bool = True) -> list[Group]:
    """The groups, in the order of their parents in ``specs``; the largest grids
    are parents."""
    if not derive:
        return [Group(name) for name in specs]
    parsed = {n: parse_spec(s) for n, s in specs.items()}
    order = sorted(specs, key=lambda n: -parsed[n].n_cells)  # stable: ties keep spec order
    groups: dict[str, Group] = {}
    taken: set[str] = set()
    for parent in order:
        if parent in taken:
            continue
        g = groups[parent] = Group(parent)
        taken.add(parent)
        for other in order:
            if other in taken:
                continue
            if derivable(specs[other], specs[parent]):
                g.children.append(other)
            elif shares_data(parsed[parent], parsed[other]):
                g.variants.append(other)
            else:
                continue
            taken.add(other)
    return [groups[n] for n in specs if n in groups]


def run_order(groups: list[Group], specs: dict[str, dict]) -> list[Group]:
    """The groups in the order their units go to the pool: the most experiments
    first (then the most records), so that its report part (findings, and figures
    per experiment) is made while the others run, and the one left after the last
    unit is the smallest (docs/performance.md#one-pass)."""
    cells = {n: parse_spec(s).n_cells for n, s in specs.items()}
    return sorted(groups, key=lambda g: (-len(g.names), -sum(cells[n] for n in g.names)))


def mc_limit(spec) -> int:
    return spec.reps if spec.mc_reps is None else spec.mc_reps


def normals_drawn(specs: dict[str, dict], groups: list[Group]) -> dict[str, int]:
    """Normal random numbers each experiment draws in this plan: its data (none when
    it takes or shares another's), its Monte Carlo runs beyond its parent's, its
    bootstrap resamples."""
    out = {}
    for g in groups:
        parent = parse_spec(specs[g.parent])
        for name in g.names:
            s = parse_spec(specs[name])
            total = 0
            for x in s.systems:
                n, m, p = x.n, x.m, x.p
                # random numbers of one dataset per N, summed over the N grid
                per_set = dataset_draws(
                    np.array(s.N), n=n, m=m, T0=s.T0, x0_std=s.x0_std, draws=s.draws
                )
                per_set = int(per_set.sum())
                if name == g.parent:
                    total += len(s.sigma_w) * s.reps * per_set
                if s.bounds_method == "bootstrap":
                    total += len(s.sigma_w) * s.reps * s.boot_reps * per_set
                if s.has("cost"):
                    mc = min(s.reps, mc_limit(s))
                    if name != g.parent:
                        mc -= min(mc, min(parent.reps, mc_limit(parent)))
                    total += len(s.sigma_w) * len(s.N) * mc * s.mc_runs * s.horizon * (m + n + p)
            out[name] = int(total)
    return out


def select_experiments(specs: dict[str, dict], only) -> dict[str, dict]:
    """The specs of the experiments named in ``only`` (None: all), in preset order."""
    if only is None:
        return specs
    names = [x.strip() for x in (only.split(",") if isinstance(only, str) else only)]
    names = [x for x in names if x]
    unknown = [x for x in names if x not in specs]
    if unknown or not names:
        raise ReproduceError(
            f"--only: unknown experiment {', '.join(unknown) or '(none given)'}; "
            f"the preset has {', '.join(specs)}"
        )
    return {n: s for n, s in specs.items() if n in names}
