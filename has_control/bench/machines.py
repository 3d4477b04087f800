"""The machine study (docs/machines.md): the documented path, experiment ->
identify -> tune, on seeded simulated machines that differ from the model in
structure, each against that machine's own best gains and the manual gains.

A machine is the project's plant with options the model lacks (a second-order
spool, a sample of command delay, Coulomb and Stribeck friction, quantised
sensors, velocity differentiated from position), its Table 1 parameters each
10-30 % off the model's (a seeded sign and size), a 5 mm spool travel, the
sensor noise of ``config/scenarios.yaml``. What the user knows: the model
(``config/*.yaml``), the sensors (noise, resolutions, how velocity is made)
and the spool's travel: a datasheet's facts. What the path learns of the
machine comes from the two shipped experiments only.

For each machine and gains: J on the machine, against the best J found by
tuning on the machine itself with the same settings; the share of samples
whose command is at the spool's travel (within 2 %, the watchdog's test); and
whether identify called its model adequate. Tuned on the identified model:
``path`` with the paper's J, ``req`` with ``config/requirements_machine.yaml``
(the documented settings for a real machine), ``robust`` (``--robust``) over
``config/scenarios_machine.yaml``; each vouched for above the validated band
(:mod:`has_control.tuning.vouch`). The documented path ends with the guarded
deployment (:mod:`has_control.deploy.guarded`, in process on the machine,
with the comparison over one period of the reference): ``deployed`` is the
gains it kept (the requirements' answer, or the manual gains when the
answer measured no better than they did), and the documented column's J.

``--drawn N`` studies machines drawn (seeded) from the acceptance class, none
of them looked at while the path was designed: the held-out check.
``--reuse JSON`` takes each machine's ``best`` and ``path`` gains from an
earlier study (their code unchanged, the same bits) and reruns the rest.

``python -m has_control.bench.machines [--machines NAME ...] [--drawn N] [--evaluations N] [--robust]
[--requirements FILE] [--reuse JSON] [--json FILE]``. A study, not a test: it prints what it measured.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from has_control.config import CONFIG_DIR, build_config, flatten, load_config, load_yaml
from has_control.core.episode import evaluate, simulate
from has_control.core.params import MANUAL_GAINS, Config, Plant
from has_control.deploy.guarded import DeploymentPlan, deploy_in_process, reference_period
from has_control.identify.data import Experiment, experiment_from_trace
from has_control.identify.params_out import params_yaml
from has_control.identify.structures import select_structure
from has_control.tuning.requirements import load_requirements
from has_control.tuning.tuner import load_tuning, make_objective, robust_tuning, tune

#: The sensors' noise of config/scenarios.yaml, read by the plant (as a machine's are) and the spool's travel.
SENSORS = {"noise.position": 1.0e-6, "noise.velocity": 1.0e-4, "noise.pressure_cap": 1.0e4,
           "noise.pressure_rod": 1.0e4, "noise.added_by": "plant", "plant.valve_limit": 5.0e-3}
#: Table 1 parameters a machine has off the model's.
VARIED = ("mass", "damping", "bulk_modulus", "leakage", "valve_gain")
#: The two shipped experiments and the noise seeds of their recordings.
EXPERIMENTS = (("identify.yaml", 11), ("identify_valve.yaml", 12))
#: The documented requirements of a real machine (tune --requirements).
REQUIREMENTS = CONFIG_DIR / "requirements_machine.yaml"
#: A command within this share of the travel counts as the spool at its stop (the watchdog's level).
AT_STOP = 0.98


@dataclass(frozen=True)
class Machine:
    """One simulated machine: ``plant`` its ``plant.*`` options beyond the
    varied Table 1 parameters, ``sensors`` its ``noise.*`` beyond SENSORS."""

    name: str
    text: str
    plant: dict
    sensors: dict
    seed: int

    def truth(self) -> dict:
        """The machine's ``plant.*``: Table 1 each 10-30 % off (seeded), then the options."""
        rng = np.random.default_rng(1000 + self.seed)
        model = load_config().actuator
        off = {f"plant.{k}": float(getattr(model, k) * (1.0 + rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 0.3)))
               for k in VARIED}
        return {**off, **{f"plant.{k}": v for k, v in self.plant.items()}}

    def known(self, base: Config | None = None) -> Config:
        """What the user configures: ``base`` (default the model) with the machine's sensors and travel."""
        return build_config({**SENSORS, **{f"noise.{k}": v for k, v in self.sensors.items()}},
                            source=f"the sensors of {self.name}", base=base or load_config())

    def actual(self, model: Config) -> Config:
        """``model`` (a controller's configuration) run on this machine: its plant replaced whole."""
        flat = {k[len("plant."):]: v for k, v in {**SENSORS, **self.truth()}.items() if k.startswith("plant.")}
        return dataclasses.replace(model, plant=Plant(**flat))


_DERIVED = {"velocity_source": "derived", "velocity_filter_frequency": 200.0}
_QUANTISED = {"position_resolution": 1.0e-6, "pressure_resolution": 1.0e3}
_FRICTION = {"friction_coulomb": 200.0, "friction_stribeck": 300.0}

#: The machines of the study: one idea each, then all of them.
MACHINES = (
    Machine("in-class", "Table 1 off, a 1.5 ms first-order valve lag", {"valve_time_constant": 1.5e-3}, {}, 1),
    Machine("friction-sensors", "Coulomb 200 N, Stribeck 300 N; 1 um / 1 kPa sensors; velocity from position",
            _FRICTION, {**_QUANTISED, **_DERIVED}, 2),
    Machine("spool-100", "a 100 Hz second-order spool (zeta 0.7)",
            {"valve_frequency": 100.0, "valve_damping_ratio": 0.7}, {}, 3),
    Machine("spool-80-delay", "an 80 Hz spool (zeta 0.6), one sample of delay, velocity from position",
            {"valve_frequency": 80.0, "valve_damping_ratio": 0.6, "delay": 1}, _DERIVED, 4),
    Machine("spool-150-friction", "a 150 Hz spool (zeta 0.8), Coulomb 150 N",
            {"valve_frequency": 150.0, "valve_damping_ratio": 0.8, "friction_coulomb": 150.0,
             "friction_stribeck": 150.0}, {}, 5),
    Machine("all", "a 120 Hz spool (zeta 0.65), delay, friction, quantised sensors, velocity from position",
            {"valve_frequency": 120.0, "valve_damping_ratio": 0.65, "delay": 1, **_FRICTION},
            {**_QUANTISED, **_DERIVED}, 6),
)


#: The most machines --drawn draws.
DRAWN_MAX = 20


def drawn_machines(n: int, seed: int = 0) -> tuple[Machine, ...]:
    """``n`` machines drawn from the acceptance class (seeded), none of them
    looked at while the path was designed: a second-order spool of 80-150 Hz
    (zeta 0.5-0.9), no delay or one sample, Coulomb 0-250 N and Stribeck
    0-300 N friction, quantised sensors or not, velocity from position or not;
    Table 1 off as every machine's (its own seed)."""
    rng = np.random.default_rng(7000 + seed)
    out = []
    for k in range(1, n + 1):
        f, z = float(rng.uniform(80.0, 150.0)), float(rng.uniform(0.5, 0.9))
        delay, fc, fs = int(rng.integers(0, 2)), float(rng.uniform(0.0, 250.0)), float(rng.uniform(0.0, 300.0))
        quantised, derived = bool(rng.integers(0, 2)), bool(rng.integers(0, 2))
        text = (f"a {f:.0f} Hz spool (zeta {z:.2f}), {delay} sample(s) of delay, Coulomb {fc:.0f} N, "
                f"Stribeck {fs:.0f} N{', quantised sensors' if quantised else ''}"
                f"{', velocity from position' if derived else ''}")
        plant = {"valve_frequency": f, "valve_damping_ratio": z, "delay": delay,
                 "friction_coulomb": fc, "friction_stribeck": fs}
        sensors = {**(_QUANTISED if quantised else {}), **(_DERIVED if derived else {})}
        out.append(Machine(f"drawn-{k}", text, plant, sensors, 100 + 10 * seed + k))
    return tuple(out)


def recording(machine: Machine, experiment: str, seed: int) -> Experiment:
    """The machine's run of the shipped experiment ``experiment`` (the manual
    gains on the model), as its sensors read it, beside what the user knows."""
    base = machine.known(load_config([CONFIG_DIR / experiment]))
    known = build_config({"noise.seed": seed}, source="seed", base=base)
    world = machine.actual(known)
    e = experiment_from_trace(simulate(world), world, name=f"{experiment} on {machine.name}")
    return Experiment(e.name, e.x, e.u, known)


def identified_model(machine: Machine, exps: list[Experiment]):
    """(the controller's configuration from the structure-selected
    identification, the selection)."""
    sel = select_structure(exps)
    text = params_yaml(exps[0].cfg, sel.chosen.result, note=f"identified on {machine.name}")
    flat = flatten(load_yaml(text, "identified")["/**"]["ros__parameters"])
    return build_config(flat, source="identified", base=machine.known()), sel


def at_stop_share(gains, cfg: Config) -> float:
    """Share of the samples of the run of ``gains`` on ``cfg`` whose command is at the spool's travel."""
    limit = cfg.plant.valve_limit
    if limit <= 0.0:
        return 0.0
    u = simulate(cfg, tuple(gains))["u"]
    return float(np.mean(np.abs(u) >= AT_STOP * limit))


def study(machine: Machine, evaluations: int, robust: bool, seed: int = 1, requirements=REQUIREMENTS,
          reuse: dict | None = None) -> dict:
    """The documented path on ``machine``; see the module. ``reuse``: an
    earlier study's row of this machine whose ``best`` and ``path`` gains are
    taken as they are (the same budget and code give the same bits)."""
    t0 = time.perf_counter()
    tuning = load_tuning().replace(seed=seed, evaluations=evaluations)
    exps = [recording(machine, name, s) for name, s in EXPERIMENTS]
    model, sel = identified_model(machine, exps)
    t_identify = time.perf_counter() - t0
    on_machine = machine.actual(model)
    kept = reuse["rows"] if reuse is not None else {}
    best = tuple(kept["best"]["gains"]) if kept else tune(on_machine, tuning, diagnostics=False).gains
    candidates = {"manual": MANUAL_GAINS.as_tuple(), "best": best}
    predicted, vouch = {}, {}
    settings = {"path": tuning, "req": tuning.replace(requirements=load_requirements(requirements))}
    if kept:
        candidates["path"], predicted["path"], vouch["path"] = (
            tuple(kept["path"]["gains"]), kept["path"]["predicted"], kept["path"]["vouch"])
        del settings["path"]
    if robust:
        settings["robust"] = robust_tuning(tuning, model, str(CONFIG_DIR / "scenarios_machine.yaml"), "cvar:0.2")
    for label, t in settings.items():
        r = tune(model, t, diagnostics=False)
        candidates[label], predicted[label] = r.gains, float(r.result.fun)
        vouch[label] = r.lines()
    plan = DeploymentPlan(MANUAL_GAINS.as_tuple(), tuple(candidates["req"]), measure=reference_period(on_machine))
    deployment = deploy_in_process(on_machine, plan)
    candidates["deployed"] = deployment.final_gains
    j = evaluate(np.array(list(candidates.values())), on_machine)
    j_best = float(j[1])
    rows = {}
    for (label, g), jm in zip(candidates.items(), j):
        rows[label] = {"gains": [float(v) for v in g], "J": float(jm), "ratio": float(jm) / j_best,
                       "at_stop": at_stop_share(g, on_machine),
                       **({"predicted": predicted[label], "vouch": vouch[label]} if label in predicted else {})}
    v = sel.chosen.result.verdict
    return {"machine": machine.name, "text": machine.text, "structure": sel.chosen.structure.name,
            "verdict": v.line() if v is not None else "", "rows": rows,
            "deployment": {"lines": deployment.lines(), **deployment.as_json()},
            "seconds": {"identify": t_identify, "total": time.perf_counter() - t0}}


def print_row(r: dict) -> None:
    print(f"{r['machine']}: {r['text']}")
    print(f"  identified as {r['structure']}; {r['verdict']}")
    for label, row in r["rows"].items():
        g = row["gains"]
        pred = f"  predicted {row['predicted']:.3e}" if "predicted" in row else ""
        print(f"  {label:<7} {g[0]:8.1f} {g[1]:8.1f} {g[2]:8.1f}  J {row['J']:.3e}  {row['ratio']:7.3g}x best  "
              f"at stop {100 * row['at_stop']:5.2f} %{pred}")
        for line in row.get("vouch", []):
            print(f"          {line}")
        if label == "deployed":
            for line in r["deployment"]["lines"]:
                print(f"          {line}")
    print(f"  ({r['seconds']['total']:.0f} s)", flush=True)


def _shown_path(path: str) -> str:
    """``path`` relative to the repository when it lies in it (the JSON names no machine's folders)."""
    p = Path(path).resolve()
    root = CONFIG_DIR.parent.resolve()
    return str(p.relative_to(root)) if p.is_relative_to(root) else str(path)


def reused_rows(path: str, evaluations: int) -> dict:
    """An earlier study's rows by machine, for ``--reuse``; ValueError (one
    line naming the file) when it cannot be read or had another budget."""
    try:
        with open(path) as f:
            earlier = json.load(f)
        budget, rows = earlier["evaluations"], {r["machine"]: r for r in earlier["rows"]}
        for name, r in rows.items():
            for label, keys in (("best", {"gains"}), ("path", {"gains", "predicted", "vouch"})):
                if not keys <= set(r["rows"][label]):
                    raise KeyError(f"{name}: rows.{label}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"--reuse {path}: not a study's JSON ({type(exc).__name__}: {exc})") from None
    if budget != evaluations:
        raise ValueError(f"--reuse {path}: its budget is {budget} evaluations, not {evaluations}")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m has_control.bench.machines", description=__doc__.splitlines()[0])
    drawn = drawn_machines(DRAWN_MAX)
    ap.add_argument("--machines", nargs="+", choices=[m.name for m in MACHINES + drawn], default=None, metavar="NAME",
                    help="the machines to study (default the six, or --drawn's)")
    ap.add_argument("--drawn", type=int, default=0, metavar="N", choices=range(DRAWN_MAX + 1),
                    help=f"study drawn-1 ... drawn-N instead of the six: machines drawn (seeded) from the "
                         f"acceptance class (N <= {DRAWN_MAX})")
    ap.add_argument("--evaluations", type=int, default=2000, help="each tuning's budget (default 2000)")
    ap.add_argument("--robust", action="store_true",
                    help="also tune robustly (config/scenarios_machine.yaml, cvar:0.2) around the identified plant")
    ap.add_argument("--requirements", default=str(REQUIREMENTS),
                    help="the requirements file of the documented path (default config/requirements_machine.yaml)")
    ap.add_argument("--reuse", default=None, metavar="JSON",
                    help="take each machine's best and paper's-J gains from an earlier study's JSON (same budget)")
    ap.add_argument("--json", default=None, help="write the rows to this file")
    args = ap.parse_args(argv)
    try:
        reuse = reused_rows(args.reuse, args.evaluations) if args.reuse else {}
    except ValueError as exc:
        print(f"{ap.prog}: {exc}", file=sys.stderr)
        return 2
    rows = []
    chosen = args.machines or [m.name for m in (drawn[:args.drawn] if args.drawn else MACHINES)]
    for m in MACHINES + drawn:
        if m.name in chosen:
            rows.append(study(m, args.evaluations, args.robust, requirements=args.requirements,
                              reuse=reuse.get(m.name)))
            print_row(rows[-1])
    if args.json:
        study_json = {"evaluations": args.evaluations, "requirements": _shown_path(args.requirements), "rows": rows}
        with open(args.json, "w") as f:
            json.dump(study_json, f, indent=1)
    return 0


def bench_objectives(repeats: int = 3, particles: int = 80) -> dict:
    """Evaluator time per candidate of each objective, best of ``repeats``
    (alternating), against today's robust tuning (cvar:0.2 over
    config/scenarios.yaml) in the same run: the paper's J, the requirements,
    the vouched nominal and the requirements over config/scenarios_machine.yaml,
    on the spool-100 machine's identified-like model (2 s episodes)."""
    base = build_config({"plant.valve_frequency": 100.0, "plant.valve_limit": 5e-3, "simulation.horizon": 2.0,
                         **{k: v for k, v in SENSORS.items() if k.startswith("noise.")}}, source="bench")
    vouched = build_config({"plant.validated_band": 258.0}, source="bench", base=base)
    ref2 = build_config({"simulation.horizon": 2.0}, source="bench")
    req = load_requirements(REQUIREMENTS)
    t = load_tuning()
    cases = {
        "robust, cvar:0.2 over config/scenarios.yaml (today)":
            (ref2, robust_tuning(t, ref2, str(CONFIG_DIR / "scenarios.yaml"), "cvar:0.2")),
        "the paper's J, nominal": (base, t),
        "requirements, nominal": (base, t.replace(requirements=req)),
        "the paper's J, vouched (band 258 Hz: 4 runs a candidate)": (vouched, t),
        "requirements, vouched": (vouched, t.replace(requirements=req)),
        "requirements over config/scenarios_machine.yaml, cvar:0.2":
            (base, robust_tuning(t, base, str(CONFIG_DIR / "scenarios_machine.yaml"), "cvar:0.2")
             .replace(requirements=req)),
    }
    k = np.random.default_rng(0).uniform([150.0] * 3, [400.0] * 3, (particles, 3))
    objectives = {name: make_objective(c, tt) for name, (c, tt) in cases.items()}
    for f in objectives.values():
        f(k[:8])                                                   # compile
    best = {name: float("inf") for name in objectives}
    for _ in range(repeats):
        for name, f in objectives.items():
            t0 = time.perf_counter()
            f(k)
            best[name] = min(best[name], time.perf_counter() - t0)
    today = best[next(iter(best))]
    return {"particles": particles, "repeats": repeats,
            "runs": {name: {"seconds_per_candidate": s / particles, "ratio": s / today} for name, s in best.items()}}


def print_objectives(r: dict) -> None:
    print(f"objective cost: {r['particles']} candidates, 2 s episodes, best of {r['repeats']} alternating; "
          "evaluator time per candidate against today's robust tuning")
    for name, run in r["runs"].items():
        print(f"  {name}: {1e3 * run['seconds_per_candidate']:.2f} ms ({run['ratio']:.2f}x)")


if __name__ == "__main__":
    raise SystemExit(main())
