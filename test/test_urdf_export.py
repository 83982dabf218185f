"""Calibrated URDF: Pinocchio FK of the exported file equals the calibrated model's FK."""
from __future__ import annotations

import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from kpi_calib_ros.core.model.kinematics import nominal_fk_function, rpy_matrix
from kpi_calib_ros.core.model.parameters import geometric_parameters
from kpi_calib_ros.core.model.robot import RobotModel
from kpi_calib_ros.io.cell import DEFAULT_CELL
from kpi_calib_ros.io.resources import cmeel_prefixes
from kpi_calib_ros.io.urdf_export import calibrated_urdf, rpy_from_matrix

KR15 = (DEFAULT_CELL.parent.parent / 'robots' / 'kr15_class.urdf').read_text()


def random_errors(robot: RobotModel, rng: np.random.Generator, scale: float) -> dict[str, float]:
    values = {}
    for joint in robot.joints:
        for c in ('tx', 'ty', 'tz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, scale * 1e-2)
        for c in ('rx', 'ry', 'rz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, scale)
        values[f'{joint.name}.offset'] = rng.normal(0, scale)
    return values


def random_q(robot: RobotModel, rng: np.random.Generator, n: int) -> np.ndarray:
    lower = np.where(np.isfinite(robot.lower), robot.lower, -np.pi)
    upper = np.where(np.isfinite(robot.upper), robot.upper, np.pi)
    return rng.uniform(lower, upper, (n, robot.n_joints))


@pytest.mark.parametrize('which', ['odd_arm', 'kr15'])
@pytest.mark.parametrize('scale', [1e-3, 0.3])
def test_exported_urdf_fk_equals_calibrated_model_fk(which, scale, odd_arm_urdf):
    urdf, base, tip = ((odd_arm_urdf, 'base', 'flange') if which == 'odd_arm'
                       else (KR15, 'base_link', 'tool0'))
    rng = np.random.default_rng(4)
    robot = RobotModel(urdf, base, tip)
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    errors = random_errors(robot, rng, scale)
    # Cell-level parameters are accepted and ignored: they are not part of a robot URDF.
    values = {**errors, 'base.x': 1.0, 'reflector.z': 0.03}
    p = params.with_values(errors)
    fk = nominal_fk_function(robot, params)

    exported = RobotModel(calibrated_urdf(urdf, robot, values), base, tip)
    worst = 0.0
    for q in random_q(robot, rng, 25):
        expected = np.array(fk(p, q))
        actual = exported.pin_tip_pose(q)
        worst = max(worst, np.abs(actual - expected).max())
    print(f'{which} errors ~{scale}: max |T_exported - T_calibrated| = {worst:.2e}')
    assert worst < 1e-9
    # ... and the calibration changed something measurable.
    assert np.abs(exported.pin_tip_pose(q) - robot.pin_tip_pose(q)).max() > 1e-5


def test_only_chain_joint_origins_change(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    out = calibrated_urdf(odd_arm_urdf, robot, random_errors(robot, np.random.default_rng(1), 1e-3))
    before = {e.get('name'): e for e in ET.fromstring(odd_arm_urdf).iter('joint')}
    after = {e.get('name'): e for e in ET.fromstring(out).iter('joint')}
    assert before.keys() == after.keys()
    for name, element in after.items():
        changed = ET.tostring(element) != ET.tostring(before[name])
        assert changed == (name in robot.joint_names), name
        # Type, axis and limits are kept: only the origin moves.
        assert element.get('type') == before[name].get('type')
        for tag in ('axis', 'limit', 'parent', 'child'):
            old, new = before[name].find(tag), element.find(tag)
            assert (old is None) == (new is None)
            if old is not None:
                assert old.attrib == new.attrib
    assert [k.get('name') for k in ET.fromstring(out).iter('link')] == \
        [k.get('name') for k in ET.fromstring(odd_arm_urdf).iter('link')]


def test_zero_errors_reproduce_the_original(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    exported = RobotModel(calibrated_urdf(odd_arm_urdf, robot, {}), 'base', 'flange')
    for q in random_q(robot, np.random.default_rng(2), 10):
        np.testing.assert_allclose(exported.pin_tip_pose(q), robot.pin_tip_pose(q), atol=1e-12)


def test_rpy_round_trip_is_exact_next_to_gimbal_lock():
    rng = np.random.default_rng(3)
    worst = 0.0
    for pitch in [np.pi / 2, -np.pi / 2, 1.5707963, np.pi / 2 - 1e-12, 0.3, -2.0]:
        for _ in range(20):
            rpy = [rng.uniform(-np.pi, np.pi), pitch, rng.uniform(-np.pi, np.pi)]
            rotation = np.array(rpy_matrix(*rpy))
            again = np.array(rpy_matrix(*rpy_from_matrix(rotation)))
            worst = max(worst, np.abs(again - rotation).max())
    assert worst < 1e-14


def test_bad_parameters_are_named(odd_arm_urdf):
    robot = RobotModel(odd_arm_urdf, 'base', 'flange')
    with pytest.raises(ValueError, match='gripper'):
        calibrated_urdf(odd_arm_urdf, robot, {'gripper.offset': 0.01})
    with pytest.raises(ValueError, match='swing.placement.tx'):
        calibrated_urdf(odd_arm_urdf, robot, {'swing.placement.tx': float('nan')})


# ---------------------------------------------------------------- every stock description
def _stock_root() -> Path:
    share = [p / 'share' / 'example-robot-data' / 'robots' for p in cmeel_prefixes()]
    found = [p for p in share if p.is_dir()]
    assert found, 'example-robot-data is a pinned requirement: pip install -r requirements.txt'
    return found[0]


_ONE_DOF = ('JointModelR', 'JointModelP')


def _longest_chain(urdf_xml: str) -> tuple[str, str] | None:
    """(base, tip) link names of the longest chain of 1-DoF joints from the root link."""
    model = pin.buildModelFromXML(urdf_xml)
    best: tuple[int, str] | None = None
    for frame in model.frames:
        if frame.type != pin.FrameType.BODY:
            continue
        support = [j for j in model.supports[frame.parentJoint] if j > 0]
        if support and all(model.joints[j].shortname().startswith(_ONE_DOF) for j in support) \
                and (best is None or len(support) > best[0]):
            best = (len(support), frame.name)
    return None if best is None else (model.frames[1].name, best[1])


def _stock_descriptions() -> list[tuple[str, str, str, str]]:
    """(id, urdf text, base, tip): every example-robot-data URDF with a chain, and the
    built-in robots."""
    cases = []
    root = _stock_root()
    for path in sorted(root.rglob('*.urdf')):
        text = path.read_text()
        try:
            chain = _longest_chain(text)
        except (ValueError, RuntimeError):
            continue  # not a URDF urdfdom reads (ur3.urdf has no robot name)
        if chain is not None:
            cases.append((str(path.relative_to(root)), text, *chain))
    builtin = DEFAULT_CELL.parent.parent / 'robots'
    for path in sorted(builtin.glob('*.urdf')):
        cases.append((f'builtin/{path.name}', path.read_text(), 'base_link', 'tool0'))
    return cases


STOCK = _stock_descriptions()


def test_the_stock_collection_is_all_there():
    """Enough descriptions to mean something: the arms with transmissions and mimic joints."""
    names = [c[0] for c in STOCK]
    assert len(names) >= 60, names
    with_transmissions = [c[0] for c in STOCK if '<transmission' in c[1]]
    with_mimic = [c[0] for c in STOCK if '<mimic' in c[1]]
    assert 'ur_description/urdf/ur10_robot.urdf' in with_transmissions
    assert len(with_transmissions) >= 20 and len(with_mimic) >= 5


def _realistic_errors(robot: RobotModel, rng: np.random.Generator) -> dict[str, float]:
    """Identified errors of the size a calibration finds: 0.5 mm, 1 mrad per component."""
    values = {}
    for joint in robot.joints:
        for c in ('tx', 'ty', 'tz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, 5e-4)
        for c in ('rx', 'ry', 'rz'):
            values[f'{joint.name}.placement.{c}'] = rng.normal(0, 1e-3)
        values[f'{joint.name}.offset'] = rng.normal(0, 1e-3)
    return values


def _working_q(robot: RobotModel, rng: np.random.Generator, n: int) -> np.ndarray:
    """Actuated joint values within the limits and within one turn (rotor joints of
    1e16 rad); mimic joints follow from them (``robot.chain_values``)."""
    lower = np.maximum(np.nan_to_num(robot.actuated_lower, neginf=-np.pi), -np.pi)
    upper = np.minimum(np.nan_to_num(robot.actuated_upper, posinf=np.pi), np.pi)
    return rng.uniform(lower, upper, (n, len(lower)))


def _elements(xml: str, tag: str) -> list[bytes]:
    return [ET.tostring(e) for e in ET.fromstring(xml).iter(tag)]


@pytest.mark.parametrize('case', STOCK, ids=[c[0] for c in STOCK])
def test_stock_description_exports_the_calibrated_kinematics(case):
    """The written URDF's forward kinematics (Pinocchio) equal the calibrated model's
    (CasADi) to 1e-9 m; transmissions and every joint off the chain are untouched."""
    name, urdf, base, tip = case
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    robot = RobotModel(urdf, base, tip)
    params = geometric_parameters(robot, np.zeros(6), np.zeros(3))
    errors = _realistic_errors(robot, rng)
    fk = nominal_fk_function(robot, params)
    p = params.with_values(errors)
    out = calibrated_urdf(urdf, robot, errors)
    exported = RobotModel(out, base, tip)
    worst, moved = 0.0, 0.0
    # Mimic joints keep their tags, the calibrated offset in them: each model expands
    # the same actuated values by its own relations.
    for x in _working_q(robot, rng, 8):
        q = robot.chain_values(x)
        actual = exported.pin_tip_pose(exported.chain_values(x))
        worst = max(worst, np.abs(actual - np.array(fk(p, q))).max())
        moved = max(moved, np.abs(actual[:3, 3] - robot.pin_tip_pose(q)[:3, 3]).max())
    assert worst < 1e-9, f'{name}: |T_exported - T_calibrated| = {worst:.2e}'
    assert moved > 1e-4, f'{name}: the written URDF is the nominal one ({moved:.2e} m)'
    # Still a URDF with the same structure: transmissions (and their <joint>s) intact.
    assert _elements(out, 'transmission') == _elements(urdf, 'transmission')
    before = {e.get('name'): ET.tostring(e) for e in ET.fromstring(urdf).findall('joint')}
    after = {e.get('name'): ET.tostring(e) for e in ET.fromstring(out).findall('joint')}
    assert before.keys() == after.keys()
    assert {n for n in after if after[n] != before[n]} <= set(robot.joint_names)


@pytest.mark.slow
def _written_urdf_points(cm, out: Path, q: np.ndarray, robot: RobotModel | None = None
                         ) -> tuple[dict, np.ndarray]:
    """calibration.yaml of ``out`` and the points (N, 3) its written URDF (or ``robot``)
    gives at ``q`` (Pinocchio forward kinematics) with its base pose and reflector offset."""
    import yaml

    from kpi_calib_ros.core.model.kinematics import pose6
    from kpi_calib_ros.io.names import CALIBRATED_URDF_FILE
    doc = yaml.safe_load((out / 'calibration.yaml').read_text())
    value = {p['name']: p['value'] for p in doc['parameters']}
    written = robot or RobotModel((out / CALIBRATED_URDF_FILE).read_text(),
                                  cm.robot.base_frame, cm.robot.tip_frame)
    base = np.array(pose6([value[f'base.{c}'] for c in ('x', 'y', 'z', 'roll', 'pitch',
                                                         'yaw')]))
    reflector = np.array([value[f'reflector.{c}'] for c in 'xyz'] + [1.0])
    return doc, np.array([(base @ written.pin_tip_pose(row) @ reflector)[:3] for row in q])


def test_cli_calibrated_urdf_of_the_stock_ur10_reproduces_the_fit(tmp_path):
    """As a user uses it: the written URDF, the base pose and reflector of calibration.yaml
    predict every measured point with the identification's own residual (the stock UR10 has
    <transmission> elements; with them edited instead of the joints it missed by mm)."""

    from kpi_calib_ros.app.measurements import load_measurements
    from kpi_calib_ros.app.simulate import simulate_campaign
    from kpi_calib_ros.cli import main
    cell = Path(__file__).parent / 'data' / 'ur10_mesh_cell.yaml'
    bag = tmp_path / 'run.mcap'
    simulate_campaign(cell, 40, bag, seed=5)
    assert main(['identify', '--cell', str(cell), '--bag', str(bag),
                 '--out', str(tmp_path / 'out')]) == 0
    cm, data, _ = load_measurements(cell, bag)
    doc, predicted = _written_urdf_points(cm, tmp_path / 'out', data.q)
    residuals = np.asarray(doc['residuals_m'])
    assert residuals.shape == data.eta.shape
    np.testing.assert_allclose(data.eta - predicted, residuals, atol=1e-9)
    # ... and the calibration is a real one: the nominal URDF misses by far more.
    _, nominal = _written_urdf_points(cm, tmp_path / 'out', data.q, cm.robot)
    assert np.sqrt(np.mean((data.eta - nominal) ** 2)) > 20 * doc['rms_m']


def test_identify_says_how_far_the_effects_the_urdf_leaves_out_move_the_point(tmp_path,
                                                                              capsys):
    """A compliance identified (joint 2 sags under its gravity torque): the written URDF
    holds the geometry only, and identify says by how much the effects move the point at
    the measured poses; the figure equals the largest distance between the calibration's
    prediction (the measured points less its residuals) and the written URDF's Pinocchio
    forward kinematics with the calibration's placement."""
    import re

    import yaml

    from kpi_calib_ros.app.measurements import load_measurements
    from kpi_calib_ros.app.simulate import simulate_campaign
    from kpi_calib_ros.cli import main
    from kpi_calib_ros.io.cell import DEFAULT_CELL
    doc = yaml.safe_load(DEFAULT_CELL.read_text())
    doc['robot']['urdf'] = str((DEFAULT_CELL.parent / doc['robot']['urdf']).resolve())
    doc['simulation'] = {'hidden_effects': {'joint_compliance:joint_2': {'c': 4.0e-6}}}
    doc.setdefault('identification', {})['model'] = 'geometric'
    cell = tmp_path / 'cell.yaml'
    cell.write_text(yaml.safe_dump(doc))
    bag = tmp_path / 'run.mcap'
    simulate_campaign(cell, 40, bag, seed=7)
    capsys.readouterr()
    assert main(['identify', '--cell', str(cell), '--bag', str(bag), '--effects',
                 'joint_compliance:joint_2', '--out', str(tmp_path / 'out')]) == 0
    text = capsys.readouterr().out
    found = re.search(r'NOTE: the calibrated URDF holds the geometry only: the effects '
                      r'joint_compliance:joint_2 move the point by up to ([0-9.]+) µm', text)
    assert found, text
    cm, data, _ = load_measurements(cell, bag)
    out, urdf = _written_urdf_points(cm, tmp_path / 'out', data.q)
    calibration = data.eta - np.asarray(out['residuals_m'])
    largest = np.linalg.norm(calibration - urdf, axis=1).max() * 1e6
    print(f"URDF leaves out up to {largest:.1f} µm")
    assert float(found.group(1)) == pytest.approx(largest, abs=0.06)
    assert largest > 50.0  # the sag is real: 4e-6 rad/(N m) under the arm's own weight
