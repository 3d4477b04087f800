"""The tuned gains as a ROS params file that a controller starts with."""
import json
import subprocess
import sys

import pytest
import rclpy

from has_control.cli import main
from has_control.nodes.controller_node import ControllerNode


@pytest.mark.ros
def test_tune_out_writes_a_params_file_the_controller_starts_with(tmp_path, domain_id):
    out = tmp_path / "session"
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "tune", "--variant", "pso-cp-tvac",
                        "--particles", "4", "--iterations", "2", "--duration", "1.5", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    tuned = json.loads((out / "tune.json").read_text())["gains"]
    for namespace in ("", "/sim0"):                       # /** reaches a controller in any namespace
        ctx = rclpy.Context()
        rclpy.init(args=["--ros-args", "--params-file", str(out / "gains.yaml")], context=ctx, domain_id=domain_id)
        node = ControllerNode(context=ctx, namespace=namespace)
        try:
            got = [node.get_parameter(f"gains.k{i}").value for i in (1, 2, 3)]
            assert got == tuned and list(node.k) == tuned          # read back, bit for bit
        finally:
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
def test_the_tuner_node_writes_the_params_file_too(tmp_path, domain_id):
    import os
    import yaml
    rec = tmp_path / "rec"
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "stack", "--tune", "--variant", "pso-cp-tvac",
                        "--iterations", "1", "--particles", "2", "--duration", "1.5", "--record", str(rec), "--json"],
                       capture_output=True, text=True, timeout=600, env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)})
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    params = yaml.safe_load((rec / "gains.yaml").read_text())["/**"]["ros__parameters"]["gains"]
    assert [params["k1"], params["k2"], params["k3"]] == out["gains"] and out["gains_file"] == str(rec / "gains.yaml")


@pytest.mark.ros
def test_parameter_descriptors_say_unit_range_choices_and_read_only(context):
    from has_control.nodes.plant_node import PlantNode
    controller, plant = ControllerNode(context=context), PlantNode(context=context)
    try:
        k1, kind, step = controller.describe_parameters(["gains.k1", "reference.kind", "simulation.step"])
        # (0, 1e6]: an open bound has no FloatingPointRange (it would need a subnormal Min)
        assert "[1/s]" in k1.description and k1.additional_constraints == "> 0 and <= 1e+06"
        assert not k1.floating_point_range and not k1.read_only
        assert "sine" in kind.additional_constraints and "chirp" in kind.additional_constraints
        assert step.read_only and "[s]" in step.description
        mass, mode = plant.describe_parameters(["actuator.mass", "mode"])
        assert mass.read_only and "[kg]" in mass.description
        assert mode.read_only and "realtime" in mode.additional_constraints
        from rclpy.parameter import Parameter
        assert not controller.set_parameters([Parameter("gains.k1", value=0.0)])[0].successful
        refused = controller.set_parameters([Parameter("gains.k1", value=-1.0)])[0]
        assert not refused.successful and "gains.k1 = -1.0" in refused.reason and "> 0 and <= 1e+06" in refused.reason
        assert "e-308" not in refused.reason and controller.get_parameter("gains.k1").value > 0
        assert controller.set_parameters([Parameter("gains.k1", value=300)])[0].successful     # a whole number
        assert controller.get_parameter("gains.k1").value == 300.0 and controller._pending[0].gains.k1 == 300.0
        damping, = plant.describe_parameters(["actuator.damping"])
        assert damping.floating_point_range[0].from_value == 0.0           # >= 0: a closed range
    finally:
        controller.destroy_node()
        plant.destroy_node()


@pytest.mark.ros
def test_a_whole_number_for_a_double_is_taken_at_start_up_and_live_settings_apply(context):
    """-p gains.k1:=300 (an integer) starts the controller with 300.0; a setting the
    node accepts at runtime takes effect (publish_internals, failsafe_samples), none is ignored."""
    from rclpy.parameter import Parameter
    from has_control.nodes.plant_node import PlantNode
    controller = ControllerNode(context=context, parameter_overrides=[Parameter("gains.k1", value=300)])
    plant = PlantNode(context=context, parameter_overrides=[Parameter("actuator.mass", value=1600)])
    try:
        assert controller.get_parameter("gains.k1").value == 300.0 and controller.k[0] == 300.0
        assert plant.get_parameter("actuator.mass").value == 1600.0
        assert controller.set_parameters([Parameter("publish_internals", value=False)])[0].successful
        assert controller._outputs.publish_internals is False
        assert plant.set_parameters([Parameter("failsafe_samples", value=3)])[0].successful
        assert plant.failsafe_samples == 3
        bad = plant.set_parameters([Parameter("failsafe_samples", value=-1)])[0]
        assert not bad.successful and plant.failsafe_samples == 3
    finally:
        controller.destroy_node()
        plant.destroy_node()


@pytest.mark.ros
def test_every_node_parameter_comes_from_a_table(context):
    """One table per component: a node declares nothing that its component's table does not hold (rclpy's
    use_sim_time and start_type_description_service, the live view's foxglove_port aside), and
    each descriptor is the table's."""
    from has_control.config import CONFIG_TABLE
    from has_control.nodes import controller_node, plant_node, tuner_node
    from has_control.nodes.parameters import descriptor
    extra = {"use_sim_time", "start_type_description_service", "foxglove_port"}
    for module, cls in ((plant_node, "PlantNode"), (controller_node, "ControllerNode"),
                        (tuner_node, "TunerNode")):
        node = getattr(module, cls)(context=context)
        try:
            tables = {**CONFIG_TABLE, **getattr(module, "TUNER_TABLE", {}), **module.OWN_PARAMETERS}
            names = set(node._parameters) - extra
            assert names <= set(tables), sorted(names - set(tables))
            for name in names:
                desc = node.describe_parameter(name)
                assert desc.description == tables[name].comment() and desc.description, name
                assert desc.additional_constraints == descriptor(tables[name]).additional_constraints, name
        finally:
            node.destroy_node()


@pytest.mark.parametrize("node", ["plant", "controller", "tuner"])
def test_a_bad_params_file_at_node_start_up_is_one_line_naming_it(node, tmp_path, capsys):
    files = {"nope.yaml": None, "bad.yaml": "a: [\n", "nops.yaml": "/**:\n  gains: {k1: 1.0}\n",
             "extra.yaml": "/**:\n  ros__parameters:\n    gains: {k1: 400.0}\nextra: 1\n",
             "mixed.yaml": "/**:\n  ros__parameters:\n    gains: {k1: [1, \"x\"]}\n",
             "twice.yaml": "/**:\n  ros__parameters:\n    gains.k1: 400.0\n    gains: {k1: 500.0}\n"}
    (tmp_path / "adir").mkdir()
    for name, text in files.items():
        if text is not None:
            (tmp_path / name).write_text(text)
    for name in [*files, "adir"]:
        with pytest.raises(SystemExit) as info:
            main([node, "--ros-args", "--params-file", str(tmp_path / name)])
        err = capsys.readouterr().err
        assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
        assert str(tmp_path / name) in err and "Traceback" not in err, err


@pytest.mark.ros
@pytest.mark.parametrize("node", ["plant", "controller"])
def test_arguments_rcl_refuses_at_node_start_up_are_one_line(node, capfd):
    """rcl logs its own [ERROR] line on fd 2 before it raises: held back, so ours is the one line."""
    for ros_args in (["-p"], ["-p", "gains.k1:=["]):
        with pytest.raises(SystemExit) as info:
            main([node, "--ros-args", *ros_args])
        lines = capfd.readouterr().err.strip().splitlines()
        assert info.value.code == 2 and len(lines) == 1, lines
        assert lines[0].startswith(f"has-control {node}: error: ROS refused the arguments: "), lines
