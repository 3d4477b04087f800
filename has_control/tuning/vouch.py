"""Gains the identified model can vouch for.

Identification validates a plant only up to a band (``plant.validated_band``,
written by ``identify --out``: 99 % of the experiments' command variance lies
below it). Above it the data say nothing: a valve that is faster or slower
than fitted, a sample of delay more, a spool the experiment never excited.
Gains whose loop works only if the model is right up there limit-cycle on the
machine (docs/machines.md). So when the plant states a validated band, a
candidate is also run on the *unseen variants* of the plant, each a change no
experiment below the band could have told apart from it:

* ``delay``: the plant's delay plus the group delay 2ζ/ω of a second-order
  lag (ζ 0.7) at UNSEEN_FACTOR (2) times the band, in samples (at least one;
  the fraction of a sample a fractional delay, ``plant.delay_fraction``, not
  rounded): dynamics the data cannot see (identify calls a valve corner
  above twice the band not determined), as a low-frequency phase lag;
* with a second-order spool: ``spool_slower`` (f_n × 0.85) and
  ``spool_damped_less`` (ζ × 0.8): a spool's bandwidth falls with the
  command's amplitude and its damping with the oil's temperature, far beyond
  the identified intervals.

A candidate is vouched for when its J on every variant is at most RATIO (2)
times its J on the identified plant and no variant diverges. The objective is
max(J, max_v J_v / RATIO): J itself where the gains are vouched for, else the
worst variant's share (with requirements: max(J_req, max_v J_w,v / RATIO),
the variants compared on the requirements' J_w without their penalties, which
are charged on the identified plant only), so the optimiser does not pick gains that rely on the
unseen (a ratio alone would let a limit-cycling plant pass, its variants as
bad as itself); where every candidate relies on it, the answer is reported
NOT VOUCHED with the variant that binds.
Without a validated band nothing changes (the reference configuration).

Under a model identify called INADEQUATE (``plant.model_adequacy:
inadequate``: residuals not white, a held-out fit below its limit) the model
vouches for nothing: the objective is the same (the variants still steer
the search away from what the band leaves unseen), but the answer is reported
NOT VOUCHED whatever its variants give, and the choice is left to the guarded
deployment, which measures the answer against the safe gains on the machine
and keeps the safe ones unless it measures better
(:mod:`has_control.deploy.stepping`). The search box is not tightened around
the safe gains: on the study's machines an INADEQUATE model still found gains
at 0.22x the manual gains' J (docs/machines.md).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from has_control.core.params import DELAY_MAX, Config

#: A variant's J over the plant's J above which the loop relies on the unseen.
RATIO = 2.0
#: The optimum of max(J, J_v / RATIO) often sits on its kink, J_v = RATIO * J,
#: where the optimiser's last digits fall on either side: a ratio within this
#: relative share above RATIO is on the kink, and vouched for.
ON_THE_KINK = 1e-3
#: The damping ratio of the lag standing for the dynamics above the band.
UNSEEN_ZETA = 0.7
#: Its corner over the validated band: identify's limit of what the data determine.
UNSEEN_FACTOR = 2.0


@dataclass(frozen=True)
class Variant:
    """One unseen variant: ``capped`` when the delay it stands for is more than the model holds (DELAY_MAX)."""

    name: str
    text: str
    cfg: Config
    capped: bool = False


def unseen_variants(cfg: Config) -> list[Variant]:
    """The plant of ``cfg`` as it may be above its validated band (see the module); none without a band."""
    band = cfg.plant.validated_band
    if band <= 0.0:
        return []
    p = cfg.plant
    extra = max(1.0, 2.0 * UNSEEN_ZETA / (2.0 * math.pi * UNSEEN_FACTOR * band) / cfg.episode.step)
    total = p.delay + p.delay_fraction + extra
    capped = total > DELAY_MAX
    total = min(float(DELAY_MAX), total)
    whole = int(total)
    fraction = total - whole if total - whole >= 1e-9 else 0.0    # a fractional delay, interpolated (no rounding)
    out = [Variant("delay", f"{total - p.delay - p.delay_fraction:.3g} more samples of delay (a lag at "
                   f"{UNSEEN_FACTOR * band:.3g} Hz)",
                   dataclasses.replace(cfg, plant=dataclasses.replace(p, delay=whole, delay_fraction=fraction)),
                   capped=capped)]
    if p.valve_frequency > 0.0:
        slower = dataclasses.replace(p, valve_frequency=0.85 * p.valve_frequency)
        out.append(Variant("spool_slower", f"the spool at {0.85 * p.valve_frequency:.3g} Hz",
                           dataclasses.replace(cfg, plant=slower)))
        out.append(Variant("spool_damped_less", f"the spool's zeta {0.8 * p.valve_damping_ratio:.2g}",
                           dataclasses.replace(cfg, plant=dataclasses.replace(
                               p, valve_damping_ratio=0.8 * p.valve_damping_ratio))))
    return out


def vouched_cost(nominal: np.ndarray, variants: np.ndarray) -> np.ndarray:
    """The objective: max(J, J_v / RATIO over the variants) of ``nominal``
    (P,) and ``variants`` (P, V): J itself wherever the gains are vouched for."""
    out = np.maximum(nominal, np.max(variants, axis=1) / RATIO) if variants.shape[1] else nominal
    return np.where(np.isfinite(out), out, np.inf)


def vouch_report(names: list[str], texts: list[str], nominal: float, variants: np.ndarray,
                 capped: bool = False, inadequate: bool = False) -> dict:
    """Whether one answer is vouched for: its J on each variant over its J on
    the plant (never when ``capped``: the band is too low to stand for; never
    when ``inadequate``: identify called the model INADEQUATE)."""
    rows = [{"variant": n, "text": t, "J": float(j), "ratio": float(j / nominal) if nominal > 0 else math.inf}
            for n, t, j in zip(names, texts, variants)]
    worst = max(rows, key=lambda r: r["ratio"]) if rows else None
    ok = (all(math.isfinite(r["ratio"]) and r["ratio"] <= RATIO * (1.0 + ON_THE_KINK) for r in rows)
          and not capped and not inadequate)
    return {"vouched": ok, "ratio_limit": RATIO, "variants": rows, "worst": worst["variant"] if worst else None,
            "band_too_low": bool(capped), "model_inadequate": bool(inadequate)}


def vouch_line(report: dict, band: float) -> str:
    """One line: vouched, or NOT VOUCHED and why."""
    if report.get("model_inadequate"):
        w = next((r for r in report["variants"] if r["variant"] == report["worst"]), None)
        seen = (f"; its worst unseen variant, {w['text']}, gives {w['ratio']:.3g}x (limit {RATIO:g}x)"
                if w is not None else "")
        return ("NOT VOUCHED: the identified model is INADEQUATE (identify's verdict): its J is not the machine's"
                f"{seen}; the deployment decides: has-control deploy measures these gains against the safe ones "
                "on the machine and keeps the safe gains unless these measure better")
    if report.get("band_too_low"):
        return (f"NOT VOUCHED: the validated band ({band:.3g} Hz) is too low to vouch for any gains (the dynamics "
                f"it leaves unseen exceed {DELAY_MAX} samples of delay); record config/identify_valve.yaml too")
    w = next(r for r in report["variants"] if r["variant"] == report["worst"])
    head = "vouched" if report["vouched"] else "NOT VOUCHED"
    return (f"{head}: the gains hold where identification did not look (above {band:.3g} Hz): the worst "
            f"unseen variant, {w['text']}, gives {w['ratio']:.3g}x the plant's J (limit {RATIO:g}x)"
            if report["vouched"] else
            f"{head}: on {w['text']} the gains give {w['ratio']:.3g}x the identified plant's J (limit {RATIO:g}x): "
            f"the loop depends on dynamics above the validated band ({band:.3g} Hz) and no gains of the search box "
            "did better; deploy under the watchdog only (has-control deploy), or validate higher "
            "(config/identify_valve.yaml)")
