"""Another MJCF model of the Go2 (sim.external_model): a file written the way third-party Go2
models are (MuJoCo Menagerie's layout: an unnamed free joint, feet named by their leg, motors in
the SDK's order, a keyframe, visual meshes whose files a copy may lack) becomes the model
Go2Sim drives, simulating exactly as the same robot built from the URDF; what it cannot take is
refused in one line; the transfer check runs on it and keeps its pages apart."""

from __future__ import annotations

import json
import re

import mujoco
import numpy as np
import pytest

from calib.joints import EFFORT_LIMIT, MODEL_JOINT_NAMES, SDK_JOINT_NAMES
from sim.effects import FloorSoftness, FootFriction, FootPayload, LinkMass
from sim.external_model import build_go2_spec_from_mjcf
from sim.go2 import Go2Sim, SimConfig, build_model_for, stand_pose
from sim.model import build_go2_spec, check_joint_order


def _urdf_xml() -> str:
    spec = build_go2_spec()
    spec.compile()
    return spec.to_xml()


def _third_party(xml: str) -> str:
    """The URDF model's MJCF rewritten as a hand-written Go2 file would be."""
    xml = xml.replace('<joint name="base_free" type="free"/>', "<freejoint/>")
    xml = re.sub(r'\s*<site name="(?:(?:FL|FR|RL|RR)_(?:foot|imu)|imu)"[^>]*/>', "", xml)
    for leg in ("FL", "FR", "RL", "RR"):
        xml = xml.replace(f'<geom name="{leg}_foot"', f'<geom name="{leg}"')
    xml = re.sub(r"\s*<sensor>.*?</sensor>", "", xml, flags=re.DOTALL)
    motors = "".join(f'<motor name="{n}" joint="{n}_joint" ctrlrange="-30 30"/>'
                     for n in SDK_JOINT_NAMES)
    xml = re.sub(r"<actuator>.*?</actuator>", f"<actuator>{motors}</actuator>", xml, flags=re.DOTALL)
    qpos = " ".join(["0 0 0.3 1 0 0 0"] + [f"{q:g}" for q in stand_pose()])
    xml = xml.replace("</mujoco>", f'<keyframe><key name="home" qpos="{qpos}" ctrl="'
                      + " ".join(["0"] * 12) + '"/></keyframe></mujoco>')
    xml = xml.replace("<asset>", '<asset><mesh name="shell" file="no_such_shell.obj"/>', 1)
    return re.sub(r'(<body name="base">\s*<inertial[^>]*/>)',
                  r'\1<geom type="mesh" mesh="shell" contype="0" conaffinity="0"/>', xml, count=1)


@pytest.fixture(scope="module")
def third_party(tmp_path_factory):
    path = tmp_path_factory.mktemp("go2") / "go2.xml"
    path.write_text(_third_party(_urdf_xml()))
    return path


def test_a_third_party_file_gets_what_the_simulator_reads(third_party):
    m = build_model_for(SimConfig(model_xml=str(third_party)))
    check_joint_order(m)  # the hinges, and motors in model order, not the file's SDK order
    assert tuple(m.actuator(i).name for i in range(m.nu)) == MODEL_JOINT_NAMES
    np.testing.assert_allclose(m.actuator_ctrlrange[:, 1], np.tile(EFFORT_LIMIT, 4))
    assert m.joint("base_free").type == mujoco.mjtJoint.mjJNT_FREE
    assert m.nkey == 0 and m.nmesh == 8  # the shell, a visual mesh without its file, dropped
    for leg in ("FL", "FR", "RL", "RR"):
        assert m.geom(f"{leg}_foot").type == mujoco.mjtGeom.mjGEOM_SPHERE
        for s in ("foot", "imu"):
            assert m.site_bodyid[m.site(f"{leg}_{s}").id] == m.body(f"{leg}_calf").id
            assert m.sensor(f"{leg}_imu_gyro").dim[0] == 3
    assert m.site_bodyid[m.site("imu").id] == m.body("base").id


def test_it_simulates_as_the_urdf_model(third_party, tmp_path):
    """The same robot through the file: the URDF's model to the precision MJCF keeps, and the
    same trajectory as that MJCF compiled as it stands (with the names of ours); the effects
    still apply."""
    urdf = build_go2_spec().compile()
    adapted = build_model_for(SimConfig(model_xml=str(third_party)))
    for f in ("body_mass", "body_inertia", "body_ipos", "body_pos", "geom_size", "geom_pos",
              "geom_friction", "jnt_range", "mesh_vert"):
        np.testing.assert_allclose(getattr(adapted, f), getattr(urdf, f), atol=1e-6, err_msg=f)
    ours = tmp_path / "ours.xml"
    ours.write_text(_urdf_xml())
    effects = [FootFriction(0.5), LinkMass(1.2, "base")]
    spec = mujoco.MjSpec.from_file(str(ours))
    for e in effects:
        e.modify_spec(spec)
    runs = []
    for xml, model in ((None, spec.compile()), (str(third_party), None)):
        sim = Go2Sim(SimConfig(effects=effects, model_xml=xml), model=model)
        sim.set_command(stand_pose() + 0.1, np.zeros(12), np.full(12, 30.0), np.full(12, 1.0),
                        np.zeros(12))
        sim.run(300)
        runs.append((sim.data.qpos.copy(), sim.base_ang_vel, sim.foot_angular_velocities(),
                     sim.model.body("base").mass[0], sim.model.geom("FL_foot").friction[0]))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert runs[1][3] == pytest.approx(1.2 * 7.277, abs=1e-3) and runs[1][4] == 0.5


def test_fixed_base_and_no_floor(third_party):
    m = build_model_for(SimConfig(base="fixed", floor=False, model_xml=str(third_party)))
    assert m.nq == 12 and "floor" not in {m.geom(i).name for i in range(m.ngeom)}


@pytest.mark.parametrize("edit, message", [
    (lambda x: x.replace('name="FR_thigh_joint"', 'name="FR_thigh_pitch"'),
     "are not the Go2's in model order"),
    (lambda x: x.replace('<body name="base">', '<body name="trunk">'), "no body named 'base'"),
    (lambda x: re.sub(r'(<geom name="RL"[^>]*pos=")[^"]*"', r'\g<1>0 0 -0.25"', x),
     "'RL_calf' has no collision sphere within 10 mm of its foot frame"),
    (lambda x: re.sub(r'<body name="base">\s*<inertial[^>]*/>', '<body name="base">', x),
     "body 'base' takes its inertia from its geoms"),
    (lambda x: "<mujoco><worldbody>", "not a MuJoCo model"),
])
def test_what_it_cannot_take_is_one_line_naming_the_file(third_party, tmp_path, edit, message):
    bad = tmp_path / "bad.xml"
    bad.write_text(edit(third_party.read_text()))
    with pytest.raises(ValueError) as e:
        build_go2_spec_from_mjcf(bad)
    assert message in str(e.value) and str(e.value).startswith(str(bad))
    assert len(str(e.value).splitlines()) == 1
    with pytest.raises(ValueError, match="model file not found"):
        build_go2_spec_from_mjcf(tmp_path / "none.xml")


def test_a_floor_softness_refuses_feet_that_govern_their_contacts(third_party, tmp_path):
    f = tmp_path / "priority.xml"
    f.write_text(re.sub(r'(<geom name="(?:FL|FR|RL|RR)")', r'\1 priority="1"',
                        third_party.read_text()))
    with pytest.raises(ValueError, match="have priority over the floor"):
        build_model_for(SimConfig(effects=[FloorSoftness(0.04)], model_xml=str(f)))
    build_model_for(SimConfig(effects=[FloorSoftness(0.04)], model_xml=str(third_party)))


def test_transfer_runs_on_it_and_keeps_its_pages_apart(third_party, tmp_path, capsys):
    pytest.importorskip("onnxruntime")
    from pathlib import Path

    from policy_train.cli import main

    policy = Path(__file__).resolve().parents[1] / "policies" / "tripod_go2_v7.onnx"
    if not policy.is_file():
        pytest.skip("no shipped policy")
    out = tmp_path / "t.md"
    args = ["transfer", str(policy), "--scenarios", "nominal", "--legs", "RR", "--episodes", "1",
            "--workers", "1", "--out", str(out)]
    assert main(args + ["--model-xml", str(third_party)]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["model"]["path"] == str(third_party) and len(meta["model"]["sha256"]) == 64
    assert meta["model"]["mujoco"] == mujoco.__version__
    assert f"--model-xml {third_party}`" in out.read_text()
    urdf = tmp_path / "u.md"
    assert main(args[:-1] + [str(urdf)]) == 0
    a, b = (json.loads(p.with_suffix(".json").read_text())["episodes"] for p in (out, urdf))
    # the same robot to the precision its MJCF keeps (6 digits), so the same figures
    assert a[0]["success"] and a[0]["rate_rms"] == pytest.approx(b[0]["rate_rms"], rel=1e-3)
    # the URDF's page does not take episodes run on another model, nor the reverse
    assert main(args[:-1] + [str(urdf), "--append", "--model-xml", str(third_party)]) == 2
    assert "the page has model the URDF's" in capsys.readouterr().err
    # two pages of one policy on two models compare as the models
    capsys.readouterr()
    assert main(["compare", str(urdf.with_suffix(".json")), str(out.with_suffix(".json"))]) == 0
    assert f"| URDF | {third_party.parent.name}/go2 |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(args + ["--model-xml", str(tmp_path / "none.xml")])
    assert e.value.code == 2


def test_the_mock_robot_runs_on_it(third_party):
    """model_xml reaches the mock's simulator: the lying robot settles on the file's model as it
    does on the URDF's."""
    from hw.mock.config import MockConfig
    from hw.mock.robot import MockRobot

    feet = []
    for xml in (None, str(third_party)):
        cfg = MockConfig(listen=[], clock="lockstep", foot_imus={"all": {"enabled": False}},
                         model_xml=xml)
        with MockRobot(cfg, transport=False) as robot:
            robot.advance(0.5)
            feet.append(robot.sim.foot_positions.copy())
            keys = robot.sim.model.nkey
    assert keys == 0  # the file's model, keyframe dropped
    np.testing.assert_allclose(feet[0], feet[1], atol=1e-4)


def test_a_foot_imu_node_goes_on_a_third_party_calf(third_party):
    """Such files keep their static bodies unfused (MuJoCo's default): the node is its own
    geometry-less body on the calf, where its foot is a geom, and adds just its mass."""
    nodes = [FootPayload(0.05, leg) for leg in ("FL", "FR", "RL", "RR")]
    m0 = build_model_for(SimConfig(base="fixed", model_xml=str(third_party)))
    m1 = build_model_for(SimConfig(base="fixed", model_xml=str(third_party), effects=nodes))
    assert m1.body_subtreemass[0] == pytest.approx(m0.body_subtreemass[0] + 0.2)
    node = m1.body("FL_imu_node")
    assert m1.body_parentid[node.id] == m1.body("FL_calf").id
    np.testing.assert_allclose(m1.body_pos[node.id], [0.0, 0.0, -0.213 + 0.04])
