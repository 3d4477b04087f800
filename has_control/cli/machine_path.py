"""The machine's path, on a simulated machine whose servo valve is second order:
experiment -> identify -> tune -> guarded deployment (through the plant and
controller nodes and the controller's parameters), each step's answer with
where it came from, against the machine's own best gains.

The machine (``config/machines/demo_machine.yaml``) differs from the model in
structure (a 100 Hz second-order spool with a 5 mm travel) and in its
parameters; its sensors are those of ``config/scenarios.yaml``. What the user
knows is the model (``config/*.yaml``) and the sensors; what the project
learns of the machine comes from the two recorded experiments only.

``python -m has_control.cli.machine_path [--out DIR] [--evaluations N]``
(``scripts/demo`` runs it after the paper's table).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from has_control.common.files import write_atomic
from has_control.config import CONFIG_DIR, build_config, flatten, load_config, load_yaml
from has_control.core.episode import evaluate, simulate
from has_control.core.params import MANUAL_GAINS
from has_control.deploy.guarded import DeploymentPlan, reference_period
from has_control.identify.data import Experiment, experiment_from_trace
from has_control.identify.fit import identify
from has_control.identify.params_out import params_yaml
from has_control.identify.structures import select_structure
from has_control.tuning.requirements import load_requirements
from has_control.tuning.tuner import load_tuning, tune

MACHINE = CONFIG_DIR / "machines" / "demo_machine.yaml"
#: The documented requirements of a real machine (tune --requirements).
REQUIREMENTS = CONFIG_DIR / "requirements_machine.yaml"
SENSORS = {"noise.position": 1e-6, "noise.velocity": 1e-4, "noise.pressure_cap": 1e4, "noise.pressure_rod": 1e4,
           "noise.added_by": "plant", "plant.valve_limit": 5e-3}


def _experiment(name: str, seed: int) -> Experiment:
    """The machine's run of the shipped experiment ``name`` as its sensors read it, with what the user knows."""
    base = load_config([CONFIG_DIR / name])
    world = load_config([CONFIG_DIR / name, MACHINE])
    world = build_config({**SENSORS, "noise.seed": seed}, source="sensors", base=world)
    known = build_config({**SENSORS, "noise.seed": seed}, source="sensors", base=base)
    e = experiment_from_trace(simulate(world), world, name=f"{name} on the machine")
    return Experiment(e.name, e.x, e.u, known)


def _model_of(text: str, base):
    return build_config(flatten(load_yaml(text, "identified")["/**"]["ros__parameters"]), source="identified",
                        base=base)


def machine_path(out: Path, evaluations: int = 2000, seed: int = 1) -> dict:
    t0 = time.perf_counter()
    task = build_config(SENSORS, source="sensors", base=load_config())                  # what the user models
    tuning = load_tuning().replace(seed=seed, evaluations=evaluations)
    print(f"1. Experiments on the machine ({MACHINE.relative_to(CONFIG_DIR.parent)}): config/identify.yaml "
          "(0.2-3 Hz chirp) and config/identify_valve.yaml (3 um chirp 5-200 Hz), manual gains ...", flush=True)
    exps = [_experiment("identify.yaml", 11), _experiment("identify_valve.yaml", 12)]
    print("   from: the machine's runs as its sensors read them (simulated here; on a real machine "
          "has-control stack --config config/identify.yaml --record DIR, docs/identification.md)")
    print("2. identify, the old way (first-order valve, the old experiment alone) ...", flush=True)
    old = identify(exps[:1])
    print(f"   {old.verdict.line()}")
    print("   identify with structure selection, both experiments ...", flush=True)
    sel = select_structure(exps)
    for line in sel.table().splitlines():
        print(f"   {line}")
    print(f"   {sel.chosen.result.verdict.line()}")
    print("   from: the two recordings only (the command sent and the sensors' readings; the machine's "
          "parameters are never read)")
    new_yaml = params_yaml(exps[0].cfg, sel.chosen.result, note="structure-selected identification")
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "identified.yaml", new_yaml)
    old_model = _model_of(params_yaml(exps[0].cfg, old), task)
    new_model = _model_of(new_yaml, task)
    truth = {k: v for k, v in flatten(load_yaml(MACHINE.read_text(), str(MACHINE))["/**"]["ros__parameters"]).items()
             if k.startswith("plant.")}
    # the controller deployed with an identified.yaml runs that model; the machine is the truth
    on_machine = [build_config({**truth, "plant.valve_time_constant": 0.0}, source="the machine", base=m)
                  for m in (old_model, new_model)]
    # the machine's own best: nothing of it is unseen, so nothing to vouch for
    itself = build_config({"plant.validated_band": 0.0}, source="the machine", base=on_machine[1])
    req = tuning.replace(requirements=load_requirements(REQUIREMENTS))
    print(f"3. tune (cma-restarts, {evaluations} evaluations): the old way (the paper's J on the first-order "
          f"model), the documented way for a real machine (--requirements {REQUIREMENTS.name}, vouched above the "
          "validated band), and on the machine itself (its best gains, the paper's J, for reference) ...",
          flush=True)
    rows, notes = [], []
    for label, model, deployed, t in (("the old identification, the paper's J", old_model, on_machine[0], tuning),
                                      ("structure-selected, requirements", new_model, on_machine[1], req),
                                      ("the machine itself (best)", itself, on_machine[1], tuning)):
        r = tune(model, t, diagnostics=False)
        j_machine = float(evaluate(np.array([r.gains]), deployed)[0])
        rows.append((label, r.gains, float(r.result.fun), j_machine))
        notes.extend(f"   {label}: {line}" for line in r.lines() if "VOUCHED" in line or line.startswith("vouched"))
    machine = on_machine[1]
    j_manual = float(evaluate(np.array([MANUAL_GAINS.as_tuple()]), machine)[0])
    best = rows[-1][3]
    print(f"   {'tuned on':<40} {'k1':>8} {'k2':>8} {'k3':>8} {'predicted J':>12} {'J on machine':>13} "
          f"{'/ best':>8}")
    print(f"   {'(manual gains)':<40} {150:8.2f} {158:8.2f} {162:8.2f} {'':>12} {j_manual:13.4e} "
          f"{j_manual / best:8.3g}")
    for label, g, jp, jm in rows:
        print(f"   {label:<40} {g[0]:8.2f} {g[1]:8.2f} {g[2]:8.2f} {jp:12.4e} {jm:13.4e} {jm / best:8.3g}")
    for line in notes:
        print(line)
    print(f"   from: each identified model ({out / 'identified.yaml'}: the controller runs its actuator.*); "
          "J on the machine and its best: the simulated machine itself, which only a study can know")
    chosen = rows[1]
    print("4. guarded deployment of the requirements' gains on the machine (4 steps of 1 s, then the "
          "safe gains and the gains that held over one period of the reference each: the better measured is kept): "
          "the plant node "
          "runs the machine, the controller node the identified model; the gains move through the controller's "
          "parameters, the watchdog reads the topics (has-control deploy --plant-node; on a real machine "
          "--controller /controller) ...", flush=True)
    # the measured J is the paper's: its prediction on the identified model (the requirements' cost is J_req)
    chosen = (*chosen[:2], float(evaluate(np.array([chosen[1]]), new_model)[0]))
    dep, dep_old = _deploy(machine, on_machine[0], chosen, rows[0])
    for line in dep.lines():
        print(f"   {line}")
    print("   and of the old way's gains:")
    for line in dep_old.lines():
        print(f"   {line}")
    print("   from: the loop's own topics (command, the controller's internals and gains) during the run")
    kept = tuple(dep.final_gains)
    j_kept = float(evaluate(np.array([kept]), machine)[0])
    print(f"   the path ends on the gains the deployment kept, ({', '.join(f'{k:.2f}' for k in kept)}): J on the "
          f"machine {j_kept:.4e}, {j_kept / best:.3g}x its best ({j_kept / j_manual:.3g}x the manual gains' J)")
    print(f"The machine's path took {time.perf_counter() - t0:.0f} s; the identified plant: {out / 'identified.yaml'}")
    return {"rows": rows, "manual": j_manual, "kept": {"gains": list(kept), "J": j_kept}, "deploy": dep.as_json(),
            "deploy_old": dep_old.as_json(), "structure": sel.chosen.structure.name}


def _deploy(machine, old_machine, chosen, old):
    """The guarded deployments of step 4, through the plant and controller nodes."""
    # lazy: rclpy and the nodes load here only (the study's other steps need no ROS)
    from has_control.nodes.deploy_node import deploy_on_plant_node
    from has_control.nodes.runtime import borrowed_context
    period = reference_period(machine) or 0.0            # the final comparison over one period of the reference
    with borrowed_context() as context:
        dep = deploy_on_plant_node(machine, DeploymentPlan(MANUAL_GAINS.as_tuple(), chosen[1], measure=period),
                                   context=context, predicted_J=chosen[2])[0]
    with borrowed_context() as context:                  # the same node names again: a context of their own
        dep_old = deploy_on_plant_node(old_machine, DeploymentPlan(MANUAL_GAINS.as_tuple(), old[1], measure=period),
                                       context=context, predicted_J=old[2])[0]
    return dep, dep_old


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m has_control.cli.machine_path", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/machine", help="output directory (default out/machine)")
    ap.add_argument("--evaluations", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    machine_path(Path(args.out), args.evaluations, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
