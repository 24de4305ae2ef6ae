"""The extra runs behind the figures (workflow/rules/extra.smk) and the sample-efficiency probe
(workflow/rules/probes.smk): which variants and probe jobs a run has, and how a variant changes the settings.
"""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError
from dswm.settings.model import Settings
from dswm.sim.scenario import CALIBRATE, Scenario

VARIANT_KINDS = ("do", "K", "u")
"""``do``: the planner's imagined demand times s (``planner.imagine_scale``, paper Fig. 8 (b)); ``K``: the fleet
size; ``u``: the demand intensity times a factor, applied after calibration (paper Fig. 10)."""


@dataclasses.dataclass(frozen=True)
class Variant:
    """One extra run's one change to the main evaluation, named ``<kind><value>`` (``do0.5``, ``K8``, ``u2``)."""

    kind: str
    """One of :data:`VARIANT_KINDS`."""
    value: float
    """s (``do``), K (``K``, an integer) or the factor of u (``u``)."""

    @property
    def name(self) -> str:
        return f"{self.kind}{self.value:g}"


def parse_variant(name: str) -> Variant:
    """The :class:`Variant` named ``name`` (its :attr:`Variant.name`).

    Raises:
        ValueError: ``name`` is not ``do<s>``, ``K<integer>`` or ``u<factor>`` with a positive number.
    """
    import re

    match = re.fullmatch(r"(do|K|u)(\d+(?:\.\d+)?)", name)
    if not match or float(match[2]) <= 0 or (match[1] == "K" and not match[2].isdigit()):
        raise ValueError(f"extra-run variant {name!r}: expected do<s>, K<integer> or u<factor> with a positive "
                         f"number, e.g. do0.5, K8, u2")
    return Variant(match[1], int(match[2]) if match[1] == "K" else float(match[2]))


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


def variant_settings(settings: Settings, variant: Variant, method: str) -> Settings:
    """``settings`` with ``variant``'s change: ``method``'s ``planner.imagine_scale`` = s (do) or the scenario's
    ``n_uavs`` = K (K); the u factor is not a setting of config.yaml (see :func:`variant_train_slice`).

    Raises:
        ConfigError: a do variant of a method whose settings have no ``planner.imagine_scale``.
    """
    if variant.kind == "K":
        return dataclasses.replace(settings, scenario=dataclasses.replace(settings.scenario, n_uavs=int(variant.value)))
    if variant.kind != "do":
        return settings
    m = settings.methods[method]
    planner = getattr(m.options, "planner", None)
    if planner is None or not hasattr(planner, "imagine_scale"):
        raise ConfigError(f"config.yaml: key 'figures.do_probe.methods' names {method!r}, whose settings have no "
                          f"planner.imagine_scale (expected a method of the 'dswm' section, e.g. dswm or dswm_wo_dec)")
    options = dataclasses.replace(m.options, planner=dataclasses.replace(planner, imagine_scale=float(variant.value)))
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
