"""The extra runs behind the figures (workflow/rules/extra.smk) and the sample-efficiency probe
(workflow/rules/probes.smk): which variants and probe jobs a run has, and how a variant changes the settings.
"""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError
from dswm.settings.model import Settings
from dswm.sim.scenario import CALIBRATE, Scenario

VARIANT_KINDS = ("do", "K", "u", "D", "rho", "alg")
"""``do``: the planner's imagined demand times s (``planner.imagine_scale``, paper Fig. 8 (b)); ``K``: the fleet
size; ``u``: the demand intensity times a factor, applied after calibration (paper Fig. 10); ``D``: the largest
displacement per slot ``scenario.d_max_m``, metres (the headroom map); ``rho``: the planner's anchoring
``planner.rho``; ``alg``: value 1 only, the planner of ``dswm`` (the paper's Algorithm 1) in place of the method's
own (the foresight grid: Algorithm 1 on persistence and on the true maps)."""
ALGORITHM_1 = "dswm"
"""The method whose planner an ``alg1`` change puts in place (the paper's Algorithm 1 as written)."""
_TOKEN = r"(do|K|u|D|rho|alg)(\d+(?:\.\d+)?)"


@dataclasses.dataclass(frozen=True)
class Variant:
    """One extra run's change(s) to the main evaluation, named ``<kind><value>`` per change (``do0.5``, ``K8``,
    ``u2``, ``rho0``, ``alg1``, ``D250u0.5``)."""

    kind: str
    """One of :data:`VARIANT_KINDS`: the first change."""
    value: float
    """s (``do``), K (``K``, an integer), the factor of u (``u``), D_max in metres (``D``), rho (``rho``) or 1
    (``alg``)."""
    more: tuple[tuple[str, float], ...] = ()
    """Further (kind, value) changes of the same run (the headroom map's ``D250u0.5``: D_max and u)."""

    @classmethod
    def of(cls, changes) -> "Variant | None":
        """The variant of the (kind, value) ``changes``, the first one first; None when there is none."""
        changes = list(changes)
        return cls(changes[0][0], changes[0][1], tuple(changes[1:])) if changes else None

    @property
    def changes(self) -> tuple[tuple[str, float], ...]:
        """Every (kind, value) change, the first one first."""
        return ((self.kind, self.value), *self.more)

    def get(self, kind: str, default=None):
        """The value of the change of ``kind``, or ``default`` when the variant has none."""
        return next((v for k, v in self.changes if k == kind), default)

    @property
    def name(self) -> str:
        return "".join(f"{k}{v:g}" for k, v in self.changes)


def _change(kind: str, text: str, name: str) -> tuple[str, float]:
    value = float(text)
    ok = {"K": value > 0 and text.isdigit(), "rho": 0 <= value <= 1, "alg": value == 1}.get(kind, value > 0)
    if not ok:
        raise ValueError(f"extra-run variant {name!r}: change {kind}{text} (expected do<s>, K<integer> or u<factor> "
                         f"with a positive number, e.g. do0.5, K8, u2; D<metres> > 0, rho<r> in [0, 1], alg1)")
    return kind, int(text) if kind == "K" else value


def parse_variant(name: str) -> Variant:
    """The :class:`Variant` named ``name`` (its :attr:`Variant.name`).

    Raises:
        ValueError: ``name`` is not a sequence of distinct changes ``do<s>``, ``K<integer>``, ``u<factor>`` (a
            positive number), ``D<metres>`` (positive), ``rho<r>`` (in [0, 1]) or ``alg1``.
    """
    import re

    if not name or not re.fullmatch(f"(?:{_TOKEN})+", name):
        raise ValueError(f"extra-run variant {name!r}: expected do<s>, K<integer> or u<factor> with a positive "
                         f"number, e.g. do0.5, K8, u2 (or the foresight and headroom variants rho<r>, alg1, "
                         f"D<metres>u<factor>)")
    changes = [_change(k, v, name) for k, v in re.findall(_TOKEN, name)]
    if len({k for k, _ in changes}) < len(changes):
        raise ValueError(f"extra-run variant {name!r}: a kind of change appears twice (expected each at most once)")
    return Variant.of(changes)


def extra_variants(settings: Settings) -> list[Variant]:
    """Every variant the extra runs of ``figures`` need, in order do, K, u. The reference points (s = 1, the
    scenario's own K, u x 1) are the main evaluations and need no run."""
    fig = settings.figures
    out = [Variant("do", float(s)) for s in fig.do_probe.scales if s != 1.0]
    out += [Variant("K", int(k)) for k in fig.scaling.fleet_sizes if k != settings.scenario.n_uavs]
    out += [Variant("u", float(f)) for f in fig.scaling.intensity_scales if f != 1.0]
    return out


def variant_methods(settings: Settings, variant: Variant) -> list[str]:
    """The methods run under ``variant``: those of ``figures.do_probe.methods`` (do) or ``figures.scaling.methods``
    (K, u) that ``methods.run`` evaluates on ``figures.dataset``."""
    fig = settings.figures
    names = fig.do_probe.methods if variant.kind == "do" else fig.scaling.methods
    return fig.present(names, settings)


def extra_jobs(settings: Settings) -> list[tuple[str, str, int]]:
    """Every (variant name, method, seed) extra evaluation on ``figures.dataset``."""
    return [(v.name, m, s) for v in extra_variants(settings) for m in variant_methods(settings, v)
            for s in settings.figures.seeds]


# ---- the foresight grid and the headroom map (figures foresight and headroom) -----------------------------
PLANNERS = {"alg1": "Algorithm 1", "plus": "DSWM+"}
"""The planners of the foresight grid: Algorithm 1 (``dswm``'s planner) and DSWM+'s (``dswm_plus``'s)."""
SOURCES = ("persistence", "model", "true")
"""The demand a planner imagines: the current map held constant, the world model anchored by rho, the true maps."""
SOURCE_METHODS = {("plus", "persistence"): "dswm_plus_persist", ("plus", "model"): "dswm_plus",
                  ("plus", "true"): "perfect", ("alg1", "persistence"): "dswm_plus_persist",
                  ("alg1", "model"): ALGORITHM_1, ("alg1", "true"): "perfect"}
"""{(planner, source): the method whose class imagines that demand}; an Algorithm 1 cell of a method of DSWM+'s
planner runs it with Algorithm 1's planner (an ``alg1`` change)."""
HEADROOM_METHODS = ("greedy", "perfect", "ceiling")
"""Greedy, Perfect forecast and the per-slot ceiling: the map's three rungs (the ceiling has no motion limit, so it
runs at the scenario's D_max only)."""


def figure_seeds(settings: Settings, dataset: str) -> list[int]:
    """The seeds of ``figures.seeds`` the profile runs on ``dataset``."""
    return [s for s in settings.figures.seeds if s in settings.seeds(dataset)]


def _datasets(settings: Settings, names) -> list[str]:
    return [d for d in names if d in settings.run.datasets]


def foresight_cells(settings: Settings, dataset: str) -> list[dict]:
    """The cells of the foresight grid on ``dataset``, planner by planner: {planner, source, rho, method, variant}.
    ``rho`` is the anchoring of a world-model cell (the planner's own, then ``figures.foresight.rho``; None for
    persistence and the true maps, which are not anchored); ``method`` the method run; ``variant`` None where the
    cell is that method's main evaluation, else the change (``rho<r>``, ``alg1``). A cell whose method
    ``methods.run`` does not evaluate on ``dataset`` has ``method`` None (not run)."""
    on = settings.methods_on(dataset)
    cells = []
    for planner in PLANNERS:
        own = SOURCE_METHODS[(planner, "model")]
        own_rho = settings.methods[own].options.planner.rho if own in on else None
        for source in SOURCES:
            method = SOURCE_METHODS[(planner, source)]
            ok = method in on and (planner == "plus" or ALGORITHM_1 in on)
            alg = [("alg", 1.0)] if planner == "alg1" and method != ALGORITHM_1 else []
            rhos = [own_rho] + [float(r) for r in settings.figures.foresight.rho if r != own_rho]
            for rho in (rhos if source == "model" else [None]):
                changes = alg + ([("rho", float(rho))] if source == "model" and rho != own_rho else [])
                variant = Variant.of(changes)
                cells.append({"planner": planner, "source": source, "rho": rho,
                              "method": method if ok else None, "variant": variant if ok else None})
    return cells


def foresight_jobs(settings: Settings) -> list[tuple[str, str, str, int]]:
    """Every (dataset, variant name, method, seed) extra evaluation of the foresight grid (its cells that are no
    main evaluation), on ``figures.foresight.datasets`` the profile runs, seeds :func:`figure_seeds`."""
    return [(d, c["variant"].name, c["method"], s) for d in _datasets(settings, settings.figures.foresight.datasets)
            for c in foresight_cells(settings, d) if c["variant"] is not None for s in figure_seeds(settings, d)]


def headroom_variant(settings: Settings, d_max_m: float, factor: float) -> Variant | None:
    """The variant of the headroom cell (D_max, u x factor): ``D<metres>`` then ``u<factor>`` unless 1 (every run
    of the map names its D_max, so its days, ``figures.headroom.eval_days``, are its own); None for the scenario's
    own cell, the main evaluation."""
    if float(d_max_m) == float(settings.scenario.d_max_m) and float(factor) == 1.0:
        return None
    more = (("u", float(factor)),) if float(factor) != 1.0 else ()
    return Variant("D", float(d_max_m), more)


def headroom_jobs(settings: Settings) -> list[tuple[str, str, str, int]]:
    """Every (dataset, variant name, method, seed) extra evaluation of the headroom map: Greedy and Perfect at every
    (D_max, factor) of ``figures.headroom`` but the scenario's own cell, the ceiling at the scenario's D_max for every
    factor but 1; on ``figures.headroom.datasets`` the profile runs, seeds :func:`figure_seeds`."""
    hr, own = settings.figures.headroom, float(settings.scenario.d_max_m)
    out = []
    for d in _datasets(settings, hr.datasets):
        on = settings.methods_on(d)
        for m in (m for m in HEADROOM_METHODS if m in on):
            for dmax in ([own] if m == "ceiling" else hr.d_max_m):
                for f in hr.intensity_scales:
                    v = headroom_variant(settings, dmax, f)
                    if v is not None:
                        out += [(d, v.name, m, s) for s in figure_seeds(settings, d)]
    return out


ROOM_FILL_ARMS = {"greedy": "greedy", "perfect": "perfect", "dswm": ALGORITHM_1, "dswm_plus": "dswm_plus",
                  "dswm_plus_persist": "dswm_plus_persist", "dswm_plus_rhok": "dswm_plus"}
"""{arm: the method it evaluates} of figure ``room_fill``: Greedy and Perfect (the room), Algorithm 1, DSWM+, its
persistence probe, and the candidate (:data:`ROOM_FILL_CANDIDATE`): DSWM+ with rho_k and gamma fitted on training
days."""
ROOM_FILL_CANDIDATE = "dswm_plus_rhok"
"""The arm whose planner takes the rho_k and gamma of the room_fill_fit job."""


def room_fill_variant(settings: Settings) -> Variant | None:
    """The headroom map's variant of the regime of ``figures.room_fill`` (None: the scenario's own cell)."""
    rf = settings.figures.room_fill
    return headroom_variant(settings, rf.d_max_m, rf.intensity_scale)


def room_fill_arms(settings: Settings) -> dict[str, str]:
    """{arm: method} of :data:`ROOM_FILL_ARMS` whose method ``methods.run`` evaluates on ``figures.room_fill.dataset``
    (none when the profile does not run that dataset, or runs no DSWM+: the figure is then not drawn)."""
    rf = settings.figures.room_fill
    if rf.dataset not in settings.run.datasets:
        return {}
    on = settings.methods_on(rf.dataset)
    if "dswm_plus" not in on:
        return {}
    return {a: m for a, m in ROOM_FILL_ARMS.items() if m in on}


def room_fill_jobs(settings: Settings) -> list[tuple[str, str, int]]:
    """Every (dataset, arm, seed) evaluation of figure ``room_fill``, seeds :func:`figure_seeds`."""
    d = settings.figures.room_fill.dataset
    return [(d, a, s) for a in room_fill_arms(settings) for s in figure_seeds(settings, d)]


def check_room_fill(settings: Settings) -> None:
    """The regime of ``figures.room_fill`` is a cell of the headroom map (its dataset, D_max and u factor).

    Raises:
        ConfigError: naming the key and the map's values.
    """
    rf, hr = settings.figures.room_fill, settings.figures.headroom
    for key, value, map_key, allowed in (("dataset", rf.dataset, "datasets", hr.datasets),
                                         ("d_max_m", rf.d_max_m, "d_max_m", hr.d_max_m),
                                         ("intensity_scale", rf.intensity_scale, "intensity_scales",
                                          hr.intensity_scales)):
        if value not in allowed:
            raise ConfigError(f"config.yaml: key 'figures.room_fill.{key}' is {value!r}, which is no cell of the "
                              f"headroom map (figures.headroom.{map_key}: {list(allowed)}); the regime is one the "
                              f"map measured")


def figure_variants(settings: Settings) -> list[Variant]:
    """Every variant of the extra runs: :func:`extra_variants`, then the foresight grid's and the headroom map's."""
    names = [v.name for v in extra_variants(settings)]
    names += [v for _, v, _, _ in foresight_jobs(settings) + headroom_jobs(settings)]
    return [parse_variant(n) for n in dict.fromkeys(names)]


def variant_days(settings: Settings, variant: Variant):
    """The day limits of an extra run: ``figures.headroom.eval_days`` for a run of the headroom map (a D change),
    ``figures.foresight.eval_days`` for one of the foresight grid (rho or alg), else ``figures.eval_days``."""
    fig = settings.figures
    kinds = {k for k, _ in variant.changes}
    if "D" in kinds:
        return fig.headroom.eval_days
    if kinds & {"rho", "alg"}:
        return fig.foresight.eval_days
    return fig.eval_days


def variant_settings(settings: Settings, variant: Variant, method: str) -> Settings:
    """``settings`` with ``variant``'s changes: the scenario's ``n_uavs`` = K (K) or ``d_max_m`` (D); ``method``'s
    ``planner.imagine_scale`` = s (do), ``planner.rho`` (rho) or its whole planner replaced by Algorithm 1's, the
    planner of ``dswm`` (alg). The u factor is not a setting of config.yaml (see :func:`variant_train_slice`).

    Raises:
        ConfigError: a do, rho or alg change of a method whose settings have no planner, or an alg change where
            ``methods.run`` has no ``dswm``.
    """
    for kind, value in variant.changes:
        if kind == "K":
            settings = dataclasses.replace(settings, scenario=dataclasses.replace(settings.scenario,
                                                                                  n_uavs=int(value)))
        elif kind == "D":
            settings = dataclasses.replace(settings, scenario=dataclasses.replace(settings.scenario,
                                                                                  d_max_m=float(value)))
        elif kind in ("do", "rho", "alg"):
            settings = _with_planner(settings, method, kind, value)
    return settings


_PLANNER_KEYS = {"do": ("figures.do_probe.methods", "imagine_scale"), "rho": ("figures.foresight", "rho"),
                 "alg": ("figures.foresight", "proposal")}


def _with_planner(settings: Settings, method: str, kind: str, value: float) -> Settings:
    """``settings`` with one planner change of ``method`` (a do, rho or alg change)."""
    key, field = _PLANNER_KEYS[kind]
    m = settings.methods[method]
    planner = getattr(m.options, "planner", None)
    if planner is None or not hasattr(planner, field):
        raise ConfigError(f"config.yaml: key {key!r} names {method!r}, whose settings have no planner.{field} "
                          f"(expected a method of the 'dswm' section, e.g. dswm or dswm_wo_dec)")
    if kind == "alg":
        if ALGORITHM_1 not in settings.methods:
            raise ConfigError(f"config.yaml: key 'figures.foresight' runs Algorithm 1's planner, the planner of "
                              f"{ALGORITHM_1!r}, which 'methods.run' does not list (add it, or leave the grid out)")
        planner = settings.methods[ALGORITHM_1].options.planner
    else:
        planner = dataclasses.replace(planner, **{field: float(value)})
    options = dataclasses.replace(m.options, planner=planner)
    return dataclasses.replace(settings, methods={**settings.methods, method: dataclasses.replace(m, options=options)})


def scale_intensity(scenario: Scenario, factor: float) -> Scenario:
    """``scenario`` with u times ``factor`` (a u variant's ``intensity_scale``); u must be a number already
    (:func:`calibrated_scenario` first).

    Raises:
        ValueError: u is still ``calibrate``.
    """
    if factor == 1.0:
        return scenario
    if scenario.calibrates:
        raise ValueError(f"scenario.demand_intensity is {CALIBRATE!r}: resolve u from the calibrate rule's record "
                         f"(calibrated_scenario) before multiplying it by {factor}")
    return dataclasses.replace(scenario, demand_intensity=float(scenario.demand_intensity) * float(factor))


# ---- the sample-efficiency probe (workflow/rules/probes.smk) ------------------------------------------------
def probed_methods(settings: Settings) -> list[str]:
    """The methods of ``figures.sample_efficiency.methods`` the probe runs: those ``methods.run`` evaluates on
    ``figures.dataset`` that the ``train`` rule fits (their own training source; a method that evaluates another's
    model, e.g. ``dswm_wo_unc``, is not probed apart)."""
    fig = settings.figures
    if fig is None:
        return []
    trained = settings.trained()
    return [m for m in fig.present(fig.sample_efficiency.methods, settings) if m in trained]


def probe_jobs(settings: Settings) -> list[tuple[str, str, int]]:
    """Every (dataset, method, seed) whose train job snapshots its model and whose snapshots the probe evaluates:
    ``figures.dataset`` x :func:`probed_methods` x ``figures.seeds``."""
    if settings.figures is None:
        return []
    return [(settings.figures.dataset, m, int(s)) for m in probed_methods(settings) for s in settings.figures.seeds]
