"""Collision capsules: distances against brute force and coal, fitting, pair selection."""
import re

import casadi as ca
import coal
import numpy as np
import pinocchio as pin
import pytest

from kpi_calib_ros.core.collision.capsule_fit import capsules_from_urdf
from kpi_calib_ros.core.collision.capsules import (
    Capsule,
    CollisionScene,
    HalfSpace,
    capsule_margin,
    halfspace_margin,
    segment_distance,
)
from kpi_calib_ros.core.collision.check import _coal_capsule, verify_configuration
from kpi_calib_ros.core.errors import ConfigError

# A 6R arm with one collision primitive per link, placed off the joint axes on
# purpose, plus a fixed-joint tool link so link frame != parent joint frame.
ARM_URDF = """<?xml version="1.0"?>
<robot name="capsule_arm">
  <link name="base_link"><collision><origin xyz="0 0 0.15"/>
    <geometry><cylinder radius="0.2" length="0.3"/></geometry></collision></link>
  <link name="link_1"><collision><origin xyz="0.05 0 0.1" rpy="0 0 0.2"/>
    <geometry><box size="0.3 0.25 0.2"/></geometry></collision></link>
  <link name="link_2"><collision><origin xyz="0 0 0.3"/>
    <geometry><cylinder radius="0.08" length="0.6"/></geometry></collision></link>
  <link name="link_3"><collision><origin xyz="0.1 0 0" rpy="0 1.5707963 0"/>
    <geometry><box size="0.12 0.1 0.35"/></geometry></collision></link>
  <link name="link_4"><collision><origin xyz="0.2 0 0" rpy="0 1.5707963 0"/>
    <geometry><cylinder radius="0.05" length="0.4"/></geometry></collision></link>
  <link name="link_5"><collision><geometry><sphere radius="0.06"/></geometry></collision></link>
  <link name="link_6"><collision><origin xyz="0.03 0 0" rpy="0 1.5707963 0"/>
    <geometry><cylinder radius="0.04" length="0.06"/></geometry></collision></link>
  <link name="tool"><collision><origin xyz="0 0.02 0.05" rpy="0.3 -0.4 0.5"/>
    <geometry><box size="0.04 0.06 0.1"/></geometry></collision>
    <collision><origin xyz="0.01 0 0.1" rpy="0.2 0 0"/>
    <geometry><capsule radius="0.02" length="0.05"/></geometry></collision>
    <collision><origin xyz="0 0 0.12"/><geometry><sphere radius="0.015"/></geometry></collision>
  </link>
  <link name="meshy"><collision><geometry><mesh filename="package://nowhere/arm.stl"/>
    </geometry></collision></link>
  <link name="bare"/>
  <joint name="joint_1" type="revolute"><parent link="base_link"/><child link="link_1"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="joint_2" type="revolute"><parent link="link_1"/><child link="link_2"/>
    <origin xyz="0.15 0 0.2"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="joint_3" type="revolute"><parent link="link_2"/><child link="link_3"/>
    <origin xyz="0 0 0.6"/><axis xyz="0 1 0"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="joint_4" type="revolute"><parent link="link_3"/><child link="link_4"/>
    <origin xyz="0.2 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="joint_5" type="revolute"><parent link="link_4"/><child link="link_5"/>
    <origin xyz="0.4 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="joint_6" type="revolute"><parent link="link_5"/><child link="link_6"/>
    <origin xyz="0.05 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="tool_mount" type="fixed"><parent link="link_6"/><child link="tool"/>
    <origin xyz="0.06 0.01 0" rpy="0.4 1.2 -0.3"/></joint>
  <joint name="meshy_mount" type="fixed"><parent link="link_2"/><child link="meshy"/></joint>
  <joint name="bare_mount" type="fixed"><parent link="link_2"/><child link="bare"/></joint>
</robot>
"""
CHAIN = ['base_link', 'link_1', 'link_2', 'link_3', 'link_4', 'link_5', 'link_6']


def _brute_force(p1, q1, p2, q2, n=200_001):
    """Min over dense samples of segment 1 of the exact point-to-segment distance."""
    pts = p1 + np.linspace(0.0, 1.0, n)[:, None] * (q1 - p1)
    d2 = q2 - p2
    e = d2 @ d2
    t = np.zeros(n) if e == 0 else np.clip((pts - p2) @ d2 / e, 0.0, 1.0)
    return float(np.min(np.linalg.norm(pts - (p2 + t[:, None] * d2), axis=1)))


def _random_pairs(rng, n_each=60):
    """Segment pairs by kind: generic, parallel, crossing, collinear, point, near-parallel."""
    def unit():
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)
    out = []
    for _ in range(n_each):
        p1, d1 = rng.uniform(-1, 1, 3), unit() * rng.uniform(0.1, 1.5)
        side = np.cross(d1, unit())
        side /= np.linalg.norm(side)
        out.append(('generic', p1, p1 + d1, *(rng.uniform(-1, 1, (2, 3)))))
        p2 = p1 + side * rng.uniform(0, 0.5) + d1 * rng.uniform(-1.5, 1.5)
        out.append(('parallel', p1, p1 + d1, p2,
                    p2 + d1 * rng.choice([-1, 1]) * rng.uniform(0.1, 2)))
        centre = p1 + d1 * rng.uniform(0, 1)
        d2 = np.cross(d1, side) * rng.uniform(0.2, 1) + d1 * rng.uniform(-0.5, 0.5)
        out.append(('crossing', p1, p1 + d1, centre - d2 * rng.uniform(0, 1),
                    centre + d2 * rng.uniform(0, 1)))
        out.append(('collinear', p1, p1 + d1, p1 + d1 * rng.uniform(-1, 2),
                    p1 + d1 * rng.uniform(-1, 2)))
        point = rng.uniform(-1, 1, 3)
        out.append(('point', point, point.copy(), p1, p1 + d1))
        out.append(('points', point, point.copy(), p1, p1.copy()))
        tilt = d1 + side * np.linalg.norm(d1) * 10.0 ** rng.uniform(-9, -4)
        out.append(('near_parallel', p1, p1 + d1, p2, p2 + tilt))
    return out


@pytest.mark.slow
def test_segment_distance_equals_brute_force_and_coal():
    rng = np.random.default_rng(7)
    sym = [ca.SX.sym(n, 3) for n in ('p1', 'q1', 'p2', 'q2')]
    dist = ca.Function('d', sym, [segment_distance(*sym)])
    request = coal.DistanceRequest()
    worst = {}
    pairs = _random_pairs(rng)
    assert len(pairs) >= 400
    for kind, p1, q1, p2, q2 in pairs:
        ours = float(dist(p1, q1, p2, q2))
        r1, r2 = rng.uniform(0.0, 0.2, 2)
        theirs = coal.distance(*_coal_capsule(p1, q1, r1), *_coal_capsule(p2, q2, r2), request,
                               coal.DistanceResult())
        margin = float(capsule_margin(ca.DM(p1), ca.DM(q1), r1, ca.DM(p2), ca.DM(q2), r2))
        err = max(abs(ours - r1 - r2 - theirs), abs(margin - theirs))
        assert err < 1e-9, (kind, ours, theirs + r1 + r2)
        assert abs(ours - _brute_force(p1, q1, p2, q2)) < 1e-4, kind
        worst[kind] = max(worst.get(kind, 0.0), err)
    print('max |ours - coal| by kind:', {k: f'{v:.1e}' for k, v in worst.items()})


def test_margin_gradient_equals_finite_differences():
    rng = np.random.default_rng(3)
    x = ca.SX.sym('x', 12)
    margin = capsule_margin(x[0:3], x[3:6], 0.05, x[6:9], x[9:12], 0.07)
    value = ca.Function('m', [x], [margin])
    grad = ca.Function('g', [x], [ca.gradient(margin, x)])
    h = 1e-6
    for _ in range(200):
        x0 = rng.uniform(-1, 1, 12)
        fd = np.array([(float(value(x0 + h * e)) - float(value(x0 - h * e))) / (2 * h)
                       for e in np.eye(12)])
        assert np.allclose(np.array(grad(x0)).ravel(), fd, atol=1e-6)


def test_halfspace_margin_and_normalisation():
    floor = HalfSpace('floor', (0, 0, 2.0), 0.4)  # z >= 0.2 once normalised
    assert floor.normal == (0.0, 0.0, 1.0) and floor.offset == pytest.approx(0.2)
    m = halfspace_margin([0, 0, 1.0], [1, 0, 0.5], 0.1, floor.normal, floor.offset)
    assert float(m) == pytest.approx(0.5 - 0.2 - 0.1)
    wall = HalfSpace('wall', (1, 0, 0), -0.45)  # x >= -0.45, the paper's wall
    assert float(halfspace_margin([-0.5, 0, 1], [0, 0, 1], 0.02, wall.normal, wall.offset)) \
        == pytest.approx(-0.07)
    rng = np.random.default_rng(5)
    request = coal.DistanceRequest()
    for _ in range(100):
        n = rng.normal(size=3)
        plane = HalfSpace('p', n, rng.uniform(-1, 1))
        a, b, r = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), rng.uniform(0, 0.3)
        theirs = coal.distance(*_coal_capsule(a, b, r), coal.Halfspace(np.array(plane.normal),
                               plane.offset), coal.Transform3s(), request, coal.DistanceResult())
        assert float(halfspace_margin(a, b, r, plane.normal, plane.offset)) == \
            pytest.approx(theirs, abs=1e-12)


def _segment_point_distance(cap, pts):
    a, b = np.array(cap.a), np.array(cap.b)
    d = b - a
    t = np.zeros(len(pts)) if d @ d == 0 else np.clip((pts - a) @ d / (d @ d), 0, 1)
    return np.linalg.norm(pts - (a + t[:, None] * d), axis=1)


def _urdf_origin(xyz, rpy):
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.array(xyz, dtype=float))


def test_fitted_capsules_enclose_the_primitives_in_the_link_frame():
    rng = np.random.default_rng(11)
    caps = {c.name: c for c in capsules_from_urdf(ARM_URDF, ['link_2', 'link_3', 'link_5', 'tool'])}
    assert sorted(caps) == ['link_2', 'link_3', 'link_5', 'tool.0', 'tool.1', 'tool.2']
    assert caps['link_2'].radius == pytest.approx(0.08)
    assert caps['link_3'].radius == pytest.approx(np.hypot(0.06, 0.05))
    n = 20000

    def inside_box(size):
        return rng.uniform(-0.5, 0.5, (n, 3)) * np.array(size)

    def inside_cylinder(radius, length):
        rho, phi = radius * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
        return np.c_[rho * np.cos(phi), rho * np.sin(phi), rng.uniform(-length / 2, length / 2, n)]

    def inside_ball(radius):
        v = rng.normal(size=(n, 3))
        return (v / np.linalg.norm(v, axis=1)[:, None] * radius
                * rng.uniform(0, 1, (n, 1)) ** (1 / 3))

    # (capsule, points in the primitive frame incl. its extreme points, URDF <origin>)
    corners = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)])
    cases = [
        ('link_2', inside_cylinder(0.08, 0.6), ([0, 0, 0.3], [0, 0, 0])),
        ('link_3', np.r_[inside_box([0.12, 0.1, 0.35]), corners * [0.12, 0.1, 0.35]],
         ([0.1, 0, 0], [0, 1.5707963, 0])),
        ('link_5', inside_ball(0.06), ([0, 0, 0], [0, 0, 0])),
        ('tool.0', np.r_[inside_box([0.04, 0.06, 0.1]), corners * [0.04, 0.06, 0.1]],
         ([0, 0.02, 0.05], [0.3, -0.4, 0.5])),
        ('tool.1', np.r_[inside_cylinder(0.02, 0.05) * [1, 1, 1],
                         inside_ball(0.02) + [0, 0, 0.025]],
         ([0.01, 0, 0.1], [0.2, 0, 0])),
        ('tool.2', inside_ball(0.015), ([0, 0, 0.12], [0, 0, 0])),
    ]
    for name, local, origin in cases:
        placement = _urdf_origin(*origin)  # the URDF origin is in the LINK frame
        pts = local @ placement.rotation.T + placement.translation
        excess = _segment_point_distance(caps[name], pts) - caps[name].radius
        assert np.max(excess) < 1e-9, name
        assert caps[name].frame == name.split('.')[0]


def test_mesh_asks_for_capsules_and_a_link_without_geometry_gets_none():
    with pytest.raises(ConfigError, match='mesh.*cell file'):
        capsules_from_urdf(ARM_URDF, ['link_1', 'meshy'])
    # No <collision>: no body to check (RobotGeometry.bare_links names it to the user).
    assert capsules_from_urdf(ARM_URDF, ['bare']) == []
    with pytest.raises(ConfigError, match='not in the URDF'):
        capsules_from_urdf(ARM_URDF, ['link_9'])


def _chain_capsules(links, k_by_link=None):
    k_by_link = k_by_link or {}
    caps = []
    for link in links:
        k = k_by_link.get(link, 1)
        caps += [Capsule(link if k == 1 else f'{link}.{j}', link, (0, 0, 0), (0.1 * j, 0, 0.3),
                         0.05) for j in range(k)]
    return caps


def test_pair_counts_follow_eq_22():
    links = [f'link_{i}' for i in range(1, 7)]
    n = len(links)
    # Nothing but the robot, and the beam silenced, to count eq. 22 alone.
    silence = {frozenset({'beam', link}) for link in links}
    scene = CollisionScene(_chain_capsules(links), [], links, ignore_pairs=silence)
    assert scene.count == n * (n - 1) // 2 - (n - 1) == 10
    assert 'link_1~link_2' not in scene.labels and 'link_2~link_4' in scene.labels
    k = 3  # k capsules on the first, then on an interior link (paper, after eq. 22)
    first = CollisionScene(_chain_capsules(links, {'link_1': k}), [], links, ignore_pairs=silence)
    assert first.count == 10 + (k - 1) * (n - 2)
    inner = CollisionScene(_chain_capsules(links, {'link_3': k}), [], links, ignore_pairs=silence)
    assert inner.count == 10 + (k - 1) * (n - 3)


def test_obstacle_and_beam_pairs():
    links = [f'link_{i}' for i in range(1, 7)]
    obstacles = [HalfSpace('floor', (0, 0, 1), 0), HalfSpace('wall', (1, 0, 0), -0.45),
                 Capsule('mounting', 'base', (0, 0, -0.5), (0, 0, 0), 0.3),
                 Capsule('car_roof', 'base', (1, -1, 1), (1, 1, 1), 0.2),
                 Capsule('car_body', 'base', (1.5, -1, 0.5), (1.5, 1, 0.5), 0.5)]
    ignore = {frozenset({'link_1', 'mounting'}), frozenset({'link_1', 'floor'})}
    scene = CollisionScene(_chain_capsules(links), obstacles, links, ignore_pairs=ignore)
    labels = scene.labels
    assert 'link_1~floor' not in labels and 'link_1~mounting' not in labels
    assert 'link_1~wall' in labels and 'link_5~car_roof' in labels
    beam = [lab for lab in labels if lab.startswith('beam~')]
    # Every robot capsule, the reflector's link's too (a Z1's beam crossed its own gripper),
    # every obstacle, half-spaces included (a tracker below the floor was designed for).
    assert beam == [f'beam~link_{i}' for i in range(1, 7)] + [
        'beam~floor', 'beam~wall', 'beam~mounting', 'beam~car_roof', 'beam~car_body']
    assert scene.count == 10 + 6 * 5 - 2 + len(beam)
    with pytest.raises(ValueError, match='not in chain_links'):
        CollisionScene([Capsule('x', 'link_9', (0, 0, 0), (0, 0, 1), 0.1)], [], links)


def test_beam_is_shortened_at_the_reflector_end_against_the_robot_alone():
    """Against the robot's capsules the beam stops ``beam_end_clearance`` short of the
    reflector (the tool carrying it); against obstacles it runs to the reflector's centre:
    a reflector 8 cm from an obstacle's axis of radius 10 cm is inside it, and the
    shortened beam called that free (a probe's reflector designed 25 mm inside a
    conveyor). A half-space beyond which the tracker stands crosses every beam."""
    blocker = Capsule('blocker', 'base', (1.0, -1, 0), (1.0, 1, 0), 0.1)
    post = Capsule('post', 'base', (1.0, -1, 0), (1.0, 1, 0), 0.1)
    floor = HalfSpace('floor', (0, 0, 1), -0.5)
    scene = CollisionScene([post], [blocker, floor], ['link_1'], beam_radius=0.005,
                           beam_end_clearance=0.05,
                           ignore_pairs={frozenset({'post', 'blocker'}),
                                         frozenset({'post', 'floor'})})
    assert scene.labels == ['beam~post', 'beam~blocker', 'beam~floor']
    # Reflector 0.12 m behind the axis: both beams cross it.
    margin = scene.margins({}, [0.0, 0, 0], [1.12, 0, 0])
    assert margin[:2] == pytest.approx([-0.105, -0.105])
    # 0.15 m before it: the robot's beam stops 0.20 m from the axis, the obstacle's 0.15 m.
    margin = scene.margins({}, [0.0, 0, 0], [0.85, 0, 0])
    assert margin[:2] == pytest.approx([0.20 - 0.105, 0.15 - 0.105])
    # 0.08 m before it, the reflector inside the obstacle: refused; the robot's beam is free.
    margin = scene.margins({}, [0.0, 0, 0], [0.92, 0, 0])
    assert margin[:2] == pytest.approx([0.13 - 0.105, 0.08 - 0.105])
    assert margin[2] == pytest.approx(0.5 - 0.005)  # tracker and reflector above the floor
    below = scene.margins({}, [0.0, 0, -0.8], [0.85, 0, 0])
    assert below[2] == pytest.approx(-0.3 - 0.005)  # the tracker below it: the beam crosses


def _arm_scene():
    # urdfdom rejects (and complains about) the non-standard <capsule>; kinematics only here.
    model = pin.buildModelFromXML(re.sub(
        r'<collision>(?:(?!</collision>).)*<capsule.*?</collision>', '', ARM_URDF, flags=re.S))
    caps = capsules_from_urdf(ARM_URDF, CHAIN + ['tool'])
    # The tool is rigid on link_6: carry its capsules in link_6's frame.
    tool = model.frames[model.getFrameId('tool')].placement
    six = model.frames[model.getFrameId('link_6')].placement
    to_six = six.inverse() * tool
    caps = [c if c.frame != 'tool' else
            Capsule(c.name, 'link_6', to_six.act(np.array(c.a)), to_six.act(np.array(c.b)),
                    c.radius)
            for c in caps]
    obstacles = [HalfSpace('floor', (0, 0, 1), 0.0), HalfSpace('wall', (1, 0, 0), -0.45),
                 Capsule('mounting', 'base', (0, 0, -0.4), (0, 0, 0), 0.25),
                 Capsule('car_roof', 'base', (0.9, -0.8, 0.9), (0.9, 0.8, 0.9), 0.15),
                 Capsule('car_body', 'base', (1.2, -1.0, 0.4), (1.2, 1.0, 0.4), 0.35)]
    # What stands on the mount, and capsules that overlap by construction (the
    # base cylinder around the shoulder, the wrist's links 4 and 6) are skipped.
    ignore = {frozenset(p) for p in [('base_link', 'mounting'), ('base_link', 'floor'),
                                     ('link_1', 'mounting'), ('base_link', 'link_2'),
                                     ('link_4', 'link_6')]}
    return model, CollisionScene(caps, obstacles, CHAIN, ignore_pairs=ignore)


def _link_transforms(model, data, q):
    pin.framesForwardKinematics(model, data, q)
    return {link: data.oMf[model.getFrameId(link)].homogeneous for link in CHAIN}


def test_verifier_agrees_with_casadi_margins_on_random_configurations():
    model, scene = _arm_scene()
    data = model.createData()
    rng = np.random.default_rng(2017)
    tracker = np.array([-0.3, 1.8, 0.5])
    worst, violated = 0.0, 0
    for _ in range(200):
        q = rng.uniform(model.lowerPositionLimit, model.upperPositionLimit)
        transforms = _link_transforms(model, data, q)
        reflector = transforms['link_6'][:3, :3] @ [0.15, 0, 0] + transforms['link_6'][:3, 3]
        ours = scene.margins(transforms, tracker, reflector)
        check = verify_configuration(scene, transforms, tracker, reflector)
        assert list(check.distances) == scene.labels and len(ours) == scene.count
        theirs = np.array(list(check.distances.values()))
        worst = max(worst, float(np.max(np.abs(ours - theirs))))
        assert check.violated == [lab for lab, m in zip(scene.labels, ours) if m < 0]
        violated += not check.ok
    assert worst < 1e-9
    assert 0 < violated < 200  # both outcomes exercised
    print(f'{scene.count} pairs, max |casadi - coal| = {worst:.1e}, '
          f'{violated}/200 random configurations in collision')


def test_scene_function_gradient_and_symbolic_paths():
    model, scene = _arm_scene()
    data = model.createData()
    transforms = _link_transforms(model, data, np.array([0.3, -0.4, 0.8, 0.5, -0.7, 0.2]))
    tracker, reflector = np.array([-0.3, 1.8, 0.5]), transforms['link_6'][:3, 3]
    fun = scene.function()
    stack = scene.stack_transforms(transforms)
    x = ca.SX.sym('x', stack.size + 6)
    out = fun(ca.reshape(x[:stack.size], stack.shape), x[-6:-3], x[-3:])
    jac = ca.Function('j', [x], [ca.jacobian(out, x)])
    x0 = np.r_[stack.ravel(order='F'), tracker, reflector]
    h = 1e-6
    fd = np.column_stack([(np.array(fun(*_split(x0 + h * e, stack.shape))) -
                           np.array(fun(*_split(x0 - h * e, stack.shape)))).ravel() / (2 * h)
                          for e in np.eye(x0.size)])
    assert np.allclose(np.array(jac(x0)), fd, atol=1e-6)
    # MX symbols through the same code give the same numbers.
    mx = {f: ca.MX.sym(f, 4, 4) for f in scene.frames}
    via_mx = ca.Function('m', list(mx.values()), [scene.margins(mx, tracker, reflector)])
    assert np.allclose(np.array(via_mx(*[transforms[f] for f in scene.frames])).ravel(),
                       scene.margins(transforms, tracker, reflector), atol=1e-12)


def _split(x, shape):
    n = shape[0] * shape[1]
    return x[:n].reshape(shape, order='F'), x[n:n + 3], x[n + 3:]


def test_the_beam_is_kept_clear_of_the_tool_carrying_the_reflector():
    """The capsules of the reflector's own link were skipped: a Unitree Z1's beam crossed its
    gripper 6-9 cm from the reflector in 2 of 24 designed poses. The beam, shortened by
    ``beam_end_clearance`` at the reflector, is now checked against them too."""
    gripper = Capsule('gripper', 'link_1', (0.5, -0.1, 0.0), (0.5, 0.1, 0.0), 0.05)
    scene = CollisionScene([gripper], [], ['link_1'], beam_radius=0.005,
                           beam_end_clearance=0.05)
    assert scene.labels == ['beam~gripper']
    transforms = {'link_1': np.eye(4)}
    # The reflector 10 cm behind the gripper: the beam crosses it.
    assert scene.margins(transforms, [0.0, 0, 0], [0.6, 0, 0]) == pytest.approx([-0.055])
    # In front of it, facing the tracker: clear.
    assert scene.margins(transforms, [0.0, 0, 0], [0.45, 0, 0]) == pytest.approx(
        [0.10 - 0.055])
