"""machine.toml of a closed-chain machine: read, validated against its MJCF, errors naming file and key."""

import re
import shutil

import numpy as np
import pytest

from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import machine_dir


def test_delta_folder_loads():
    spec = MachineSpec.load(machine_dir("delta_3dof"))
    assert not spec.legacy and spec.kind == "chain"
    assert [m.name for m in spec.motors] == ["m1", "m2", "m3"]
    assert [m.joint for m in spec.motors] == ["arm1_motor", "arm2_motor", "arm3_motor"]
    assert {m.kind for m in spec.motors} == {"revolute"} and {m.unit for m in spec.motors} == {"deg"}
    assert spec.motor_columns == ("m1_cmd_deg", "m2_cmd_deg", "m3_cmd_deg")
    assert spec.target_columns[:4] == ("t1_x", "t1_y", "t1_z", "t2_x") and len(spec.target_columns) == 9
    assert spec.task.site == "tcp" and spec.task.coordinates == ("x_mm", "y_mm", "z_mm")
    assert spec.workspace["z_mm"] == (-950.0, -650.0)
    assert spec.table_axes == ("x_mm", "y_mm", "z_mm")
    with pytest.raises(TypeError):
        spec.workspace["x_mm"] = (0.0, 1.0)                 # frozen


@pytest.mark.parametrize("name", ["ocpm_2dof", "planar_2dof"])
def test_seeded_machines_are_legacy(name):
    spec = MachineSpec.load(machine_dir(name))
    assert spec.legacy and spec.kind == name and spec.model_path.name == f"{name}.xml"


@pytest.fixture
def folder(tmp_path):
    dst = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), dst)
    return dst


def _edit(folder, old, new, count=1):
    p = folder / "machine.toml"
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new, count))


@pytest.mark.parametrize("old,new,key,words", [
    ('joint = "arm3_motor"', 'joint = "hip3"', "motors[3].joint", "'hip3' is not a joint of delta_3dof.xml"),
    ('joint = "arm2_motor"', 'joint = "rod2a_u1"', None, None),               # a hinge: valid
    ('joint = "arm2_motor"', 'joint = "arm1_motor"', "motors[2].joint", "already motor"),
    ('kind = "revolute"\nrange', 'kind = "prismatic"\nrange', "motors[1].kind", "hinge joint"),
    ('range = [-35.0, 80.0]           # deg', 'range = [80.0, -35.0] # deg', "motors[1].range", "lo < hi"),
    ('zero = 0.0                      #', 'zero = "a"  #', "motors[1].zero", "finite number"),
    ('"nest1", "nest2"', '"nest1", "nest9"', "tracker.targets[2]", "'nest9' is not a site"),
    ('measure = "position"', 'measure = "pose"\nsigma = 1', "tracker.sigma", "unknown key"),
    ('sigma_mm = 0.01', 'sigma_mm = -0.01', "tracker.sigma_mm", "positive"),
    ('sigma_mm = 0.01', 'sigma_mm = 10000.0', "tracker.sigma_mm", "at most 10"),    # micrometres? (was exit 1)
    ('angle_deg = 0.1', 'angle_deg = 1e300', "errors.angle_deg", "at most 180"),   # was exit 1: a bug, SVD
    ('zero_deg = 0.1', 'zero_deg = 1e300', "errors.zero_deg", "at most 180"),
    ('position_mm = 0.5', 'position_mm = 1e300', "errors.position_mm", "at most 1000"),
    ('zero = 0.0                      #', 'zero = 0.0\nsigma = 1e300 #', "motors[1].sigma", "at most 10"),
    ('site = "tcp"', 'site = "tool"', "task.site", "'tool' is not a site"),
    ('"x_mm", "y_mm", "z_mm"]\n\n[workspace]', '"x_mm", "y_mm", "z"]\n\n[workspace]', "task.coordinates",
     "unknown coordinate 'z'"),
    ('"x_mm", "y_mm", "z_mm"]\n\n[workspace]', '"x_mm", "y_mm", "z_mm", "rz_deg"]\n\n[workspace]\n'
     'rz_deg = [-1.0, 1.0]', "task.coordinates", "4 coordinates for 3 motors"),      # a target met by chance
    ('z_mm = [-950.0, -650.0]', '', "workspace.z_mm", "every task coordinate needs"),
    ('frames = "all"', 'frames = ["rod1a", "elbow"]', "errors.frames", "'elbow' is neither"),
    ('components = ["dx", "dy", "dz", "drx", "dry", "drz"]', 'components = ["dx", "rx"]', "errors.components",
     "unknown component 'rx'"),
    ('axes = ["x_mm", "y_mm", "z_mm"]', 'axes = ["x_mm", "y_mm", "z_mm", "x_mm"]', "table.axes", "repeat"),
    # a grid key of a table without axes did nothing, silently, whatever its value (nodes = [1, 1, 1])
    ('axes = ["x_mm", "y_mm", "z_mm"]', 'axes = []', "table.nodes", "a table without axes has no grid"),
    ('home = "home"', 'home = "rest"', "machine.home", "no keyframe 'rest'"),
    # a newline in the name or title headed every CSV written with a line that was no comment
    ('name = "delta_3dof"', 'name = "two\\nlines"', "machine.name", "must be one line"),
    ('title = "Delta', 'title = "\\tDelta', "machine.title", "without control characters"),
    ('model = "delta_3dof.xml"', 'model = "delta.xml"', "machine.model", "not found"),
])
def test_bad_toml_names_file_key_and_fix(folder, old, new, key, words):
    _edit(folder, old, new)
    if key is None:
        MachineSpec.load(folder)
        return
    with pytest.raises(InputError) as exc:
        MachineSpec.load(folder)
    msg = str(exc.value)
    assert msg.startswith(str(folder / "machine.toml")), msg
    assert exc.value.field == key, msg
    assert words in msg, msg


def test_a_toml_nested_too_deep_is_one_line(folder):
    # tomllib recurses per level: was a RecursionError traceback, exit 1
    p = folder / "machine.toml"
    p.write_text(p.read_text() + "\n[deep]\nx = " + "[" * 3000 + "]" * 3000 + "\n")
    with pytest.raises(InputError, match="nested too deep") as exc:
        MachineSpec.load(folder)
    assert str(exc.value).startswith(str(p))


def test_a_joint_driven_twice_names_the_motor_that_drives_it(folder):
    # m1 = arm3_motor, m2 = arm2_motor, m3 = arm3_motor: was "already motor 2" (its place among the joints sorted)
    _edit(folder, 'joint = "arm1_motor"', 'joint = "arm3_motor"')
    with pytest.raises(InputError, match=re.escape("'arm3_motor' is already motor 1")) as exc:
        MachineSpec.load(folder)
    assert exc.value.field == "motors[3].joint"


def test_unknown_joint_lists_the_joints(folder):
    _edit(folder, 'joint = "arm3_motor"', 'joint = "hip3"')
    with pytest.raises(InputError, match=re.escape("(joints: arm1_motor, rod1a_u1")):
        MachineSpec.load(folder)


def test_missing_folder_and_file(tmp_path):
    with pytest.raises(InputError, match="machine folder not found"):
        MachineSpec.load(tmp_path / "nowhere")
    with pytest.raises(InputError, match="needs a machine.toml"):
        MachineSpec.load(tmp_path)
    (tmp_path / "machine.toml").write_text("[machine\n")
    with pytest.raises(InputError, match="cannot read machine configuration"):
        MachineSpec.load(tmp_path)


def test_joint_type_from_default_class(tmp_path):
    """The motor's joint type comes through the default classes (childclass of an ancestor body)."""
    (tmp_path / "m.xml").write_text("""<mujoco><default><default class="a"><joint type="slide"/></default>
      </default><worldbody><body childclass="a"><joint name="j"/><geom size="0.1"/>
      <site name="s"/></body></worldbody><keyframe><key name="home"/></keyframe></mujoco>""")
    (tmp_path / "machine.toml").write_text("""[machine]\nmodel = "m.xml"\n[[motors]]\njoint = "j"\n
range = [0, 10]\n[tracker]\ntargets = ["s"]\nsigma_mm = 0.01\n[task]\nsite = "s"\ncoordinates = ["x_mm"]\n
[workspace]\nx_mm = [0, 1]\n""")
    spec = MachineSpec.load(tmp_path)
    assert spec.motors[0].kind == "prismatic" and spec.motors[0].unit == "mm" and spec.motor_columns == ("m1_cmd_mm",)


def test_closures_section(folder):
    (folder / "machine.toml").write_text((folder / "machine.toml").read_text() + """
[closures]
default_n_per_mm = 1000.0
joint_springs = true
stiffness = { closure_1a = 1.0e6 }
""")
    spec = MachineSpec.load(folder)
    assert spec.closures.default_n_per_mm == 1000.0 and spec.closures.stiffness["closure_1a"] == 1e6
    assert spec.closures.joint_springs
    _edit(folder, "closure_1a = 1.0e6", "closure_9 = 1.0e6")
    with pytest.raises(InputError, match="'closure_9' is not an equality of delta_3dof.xml") as exc:
        MachineSpec.load(folder)
    assert exc.value.field == "closures.stiffness.closure_9"


def test_seeded_machine_described_as_data():
    spec = MachineSpec.load(machine_dir("ocpm_2dof") / "chain")
    assert not spec.legacy and spec.name == "ocpm_2dof" and spec.model_path.name == "ocpm_2dof.xml"
    assert spec.task.coordinates == ("phi_deg", "theta_deg") and spec.closures.joint_springs


def test_home_defaults_to_the_default_configuration_without_a_home_keyframe(folder):
    """No ``[machine] home`` and no ``home`` keyframe: the default configuration (``spec.home`` None; the twin
    closes it, tests/test_corpus.py). Naming a keyframe that does not exist stays an error; so does a default
    configuration that does not close (the Delta's platform body moved 50 mm below where its rods end)."""
    xml = folder / "delta_3dof.xml"
    xml.write_text(re.sub(r"<keyframe>.*?</keyframe>", "", xml.read_text(), flags=re.S))
    with pytest.raises(InputError, match="no keyframe 'home'"):
        MachineSpec.load(folder)                            # machine.toml names it
    toml = folder / "machine.toml"
    toml.write_text(re.sub(r"^home = .*\n", "", toml.read_text(), flags=re.M))
    spec = MachineSpec.load(folder)
    assert spec.home is None
    from pmcal.twin.closed_chain import ClosedChainTwin

    assert np.isfinite(ClosedChainTwin(spec).home_qpos).all()             # the Delta's qpos0 is assembled
    xml.write_text(xml.read_text().replace('<body name="platform" childclass="delta_3dof" pos="0 0 -0.6323765">',
                                           '<body name="platform" childclass="delta_3dof" pos="0 0 -0.6823765">'))
    with pytest.raises(InputError, match=r"default configuration does not close its loops \(gap 50"):
        ClosedChainTwin(MachineSpec.load(folder))
