"""Capsules fitted to the collision geometry of a URDF (enclosing, never smaller).

cylinder -> capsule along its axis with its radius; box -> capsule along the
longest axis with the half-diagonal of the other two as radius; sphere -> a
zero-length capsule; ``<capsule>`` passes through; the meshes of a link (STL,
DAE, OBJ as Pinocchio/coal load them) -> one enclosing capsule, or up to
``max_pieces`` along the principal axis where one is loose (:func:`fit_capsules`).
Endpoints are in the LINK frame. Mesh URIs must be absolute paths or findable by
Pinocchio through ``package_dirs`` (:mod:`kpi_calib_ros.io.resources` resolves them
the ROS way before calling here).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import replace
from typing import Any, Sequence

import coal
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision.capsule_geometry import fit_capsules
from kpi_calib_ros.core.collision.capsules import Capsule
from kpi_calib_ros.core.errors import ConfigError

__all__ = ['collision_vertices', 'capsules_from_urdf', 'collision_points']

_PRIMITIVES = ('cylinder', 'box', 'sphere')


def _link_capsule(name: str, link: str, placement: pin.SE3, half: float,
                  radius: float, axis: int = 2) -> Capsule:
    """Capsule along local ``axis`` of ``placement`` (link frame), half-length ``half``."""
    direction = placement.rotation[:, axis] * half
    centre = placement.translation
    return Capsule(name, link, centre - direction, centre + direction, radius)


def _fit(shape: Any, name: str, link: str, placement: pin.SE3) -> Capsule:
    """Smallest capsule of our family that encloses one coal primitive."""
    if isinstance(shape, (coal.Cylinder, coal.Capsule)):
        # For a cylinder the hemispherical caps cover the flat ends: segment = axis.
        return _link_capsule(name, link, placement, shape.halfLength, shape.radius)
    if isinstance(shape, coal.Sphere):
        return _link_capsule(name, link, placement, 0.0, shape.radius)
    if isinstance(shape, coal.Box):
        half = np.asarray(shape.halfSide, dtype=float)
        axis = int(np.argmax(half))
        # The segment must span the full box length: the corner at the segment's
        # end is then exactly at distance hypot(other half-sides) = radius.
        radius = float(np.linalg.norm(np.delete(half, axis)))
        return _link_capsule(name, link, placement, float(half[axis]), radius, axis)
    raise ConfigError(f'collision.capsules.{link}',
                      f'cannot fit a capsule to a {type(shape).__name__}; '
                      f'give capsules for link {link!r} in the cell file')


def _shape(col: ET.Element) -> ET.Element:
    """Return the shape element of a ``<collision>`` that :func:`_prepare` kept."""
    geometry = col.find('geometry')
    if geometry is None or not len(geometry):
        raise RuntimeError('a <collision> without <geometry> was kept: _prepare drops those')
    return geometry[0]


def _origin(element: ET.Element) -> pin.SE3:
    """URDF ``<origin>`` of a collision element: its pose in the link frame."""
    origin = element.find('origin')
    attrs = origin.attrib if origin is not None else {}
    xyz, rpy = (np.array(attrs.get(k, '0 0 0').split(), dtype=float) for k in ('xyz', 'rpy'))
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def _prepare(urdf_xml: str, link_names: Sequence[str]) -> tuple[
        dict[str, list[tuple[str, ET.Element]]], str]:
    """Collision elements per requested link and a URDF Pinocchio can load.

    urdfdom cannot parse ``<capsule>`` (it then drops every collision of that link)
    and the meshes of links we do not fit need not be found, so the cleaned URDF
    keeps the primitives everywhere and the meshes of the requested links only.
    """
    root = ET.fromstring(urdf_xml)
    links = {link.get('name'): link for link in root.findall('link')}
    per_link: dict[str, list[tuple[str, ET.Element]]] = {}
    for name in link_names:
        key = f'collision.capsules.{name}'
        if name not in links:
            raise ConfigError(key, f'link {name!r} is not in the URDF')
        items = []
        for col in links[name].findall('collision'):
            geometry = col.find('geometry')
            kind = geometry[0].tag if geometry is not None and len(geometry) else 'none'
            if kind not in _PRIMITIVES + ('capsule', 'mesh'):
                raise ConfigError(key, f'link {name!r} has {kind} collision geometry; '
                                       'give capsules for this link in the cell file')
            items.append((kind, col))
        if items:
            # A link without <collision> (a mount, a virtual wrist link) has no body to
            # collide, as in MoveIt; the caller names such links (RobotGeometry.bare_links).
            per_link[name] = items
    for link in root.findall('link'):
        keep = _PRIMITIVES + (('mesh',) if link.get('name') in per_link else ())
        for col in list(link.findall('collision')):
            geometry = col.find('geometry')
            if geometry is None or not len(geometry) or geometry[0].tag not in keep:
                link.remove(col)
        for vis in list(link.findall('visual')):
            link.remove(vis)
    return per_link, ET.tostring(root, encoding='unicode')


def _geometry(clean: str, package_dirs: Sequence[str],
              per_link: dict[str, list[tuple[str, ET.Element]]]) -> tuple[Any, Any]:
    model = pin.buildModelFromXML(clean)
    try:
        geom = pin.buildGeomFromUrdfString(model, clean, pin.GeometryType.COLLISION,
                                           package_dirs=[str(d) for d in package_dirs])
    except (ValueError, RuntimeError, OSError) as exc:
        meshes = {link: [_shape(c).get('filename') for k, c in items if k == 'mesh']
                  for link, items in per_link.items()}
        meshes = {link: uris for link, uris in meshes.items() if uris}
        raise ConfigError('robot.package_dirs',
                          f'mesh collision geometry {meshes} cannot be loaded ({exc}); searched '
                          f'{list(package_dirs)} and ROS_PACKAGE_PATH/AMENT_PREFIX_PATH; add the '
                          'package to robot.package_dirs or give capsules for these links in '
                          'the cell file') from exc
    return model, geom


def collision_vertices(urdf_xml: str, link_names: Sequence[str],
                       package_dirs: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Vertices of the collision MESHES of each link, in the link frame (m).

    Links without a mesh map to a (0, 3) array. Mesh scale is applied by the loader.
    """
    per_link, clean = _prepare(urdf_xml, link_names)
    model, geom = _geometry(clean, package_dirs, per_link)
    return {name: collision_points(model, geom, name) for name in per_link}


def capsules_from_urdf(urdf_xml: str, link_names: Sequence[str],
                       package_dirs: Sequence[str] = (), max_pieces: int = 3,
                       loose_ratio: float = 2.5) -> list[Capsule]:
    """Enclosing capsules for the URDF ``<collision>`` geometry of some links.

    cylinder -> capsule on its axis, same radius; box -> capsule along its
    longest axis, radius = half-diagonal of the other two; sphere -> zero-length
    capsule; ``<capsule radius length>`` (non-standard, along z) -> itself; all
    meshes of a link together -> :func:`~kpi_calib_ros.core.collision.capsule_geometry.fit_capsules`
    on their vertices (every vertex inside; split along the principal axis into
    up to ``max_pieces`` when one capsule is ``loose_ratio`` times the hull volume).

    Parameters
    ----------
    urdf_xml : str
        URDF document; mesh filenames absolute or findable through ``package_dirs``.
    link_names : sequence of str
        Links to fit; a link without collision elements gets no capsule.
    package_dirs : sequence of str
        Passed to Pinocchio's mesh loader.
    max_pieces : int
        Most capsules fitted to the meshes of one link.
    loose_ratio : float
        Capsule volume / convex-hull volume above which a mesh is split.

    Returns
    -------
    list of Capsule
        Endpoints in the link frame (m). Named after the link when it has one
        capsule, else ``'<link>.<k>'`` (primitives in document order, then meshes).

    Raises
    ------
    ConfigError
        A link is unknown or has collision geometry of no supported kind; a mesh cannot
        be loaded.
    """
    per_link, clean = _prepare(urdf_xml, link_names)
    model, geom = _geometry(clean, package_dirs, per_link)
    capsules = []
    for name, items in per_link.items():
        frame = model.frames[model.getFrameId(name, pin.BODY)]
        from_pin = [o for o in geom.geometryObjects if model.frames[o.parentFrame].name == name]
        primitives = [o for o in from_pin if not isinstance(o.geometry, coal.BVHModelBase)]
        shapes: list[Capsule] = []
        for kind, col in items:
            if kind == 'capsule':
                length, radius = (_shape(col).get(k) for k in ('length', 'radius'))
                if length is None or radius is None:
                    raise ConfigError(f'collision.capsules.{name}',
                                      f'link {name!r}: <capsule> needs length and radius')
                shapes.append(_link_capsule(name, name, _origin(col), 0.5 * float(length),
                                            float(radius)))
            elif kind != 'mesh':
                obj = primitives.pop(0)
                shapes.append(_fit(obj.geometry, name, name,
                                   frame.placement.inverse() * obj.placement))
        points = collision_points(model, geom, name)
        if len(points):
            shapes += [Capsule(name, name, a, b, radius)
                       for a, b, radius in fit_capsules(points, max_pieces, loose_ratio)]
        if len(shapes) > 1:
            shapes = [replace(c, name=f'{name}.{k}') for k, c in enumerate(shapes)]
        capsules += shapes
    return capsules


def collision_points(model: Any, geom: Any, link: str) -> np.ndarray:
    """Mesh vertices of ``link`` in its link frame (m), (0, 3) without meshes."""
    parts = []
    for obj in geom.geometryObjects:
        if model.frames[obj.parentFrame].name == link and isinstance(obj.geometry,
                                                                     coal.BVHModelBase):
            # Pinocchio places geometry in the parent JOINT frame; the link frame
            # differs when fixed joints were merged into that joint.
            local = model.frames[obj.parentFrame].placement.inverse() * obj.placement
            v = np.asarray(obj.geometry.vertices(), dtype=float).reshape(-1, 3)
            parts.append(v @ local.rotation.T + local.translation)
    return np.vstack(parts) if parts else np.zeros((0, 3))
