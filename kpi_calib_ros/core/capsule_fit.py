"""Capsules fitted to the collision geometry of a URDF (enclosing, never smaller).

cylinder -> capsule along its axis with its radius; box -> capsule along the
longest axis with the half-diagonal of the other two as radius; sphere -> a
zero-length capsule; ``<capsule>`` passes through; a mesh is refused with a
message asking for capsules in the cell file. Endpoints are in the LINK frame.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any, Sequence

import coal
import numpy as np
import pinocchio as pin

from kpi_calib_ros.core.collision import Capsule
from kpi_calib_ros.core.errors import ConfigError


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


def _origin(element: ET.Element) -> pin.SE3:
    """URDF ``<origin>`` of a collision element: its pose in the link frame."""
    origin = element.find('origin')
    attrs = origin.attrib if origin is not None else {}
    xyz, rpy = (np.array(attrs.get(k, '0 0 0').split(), dtype=float) for k in ('xyz', 'rpy'))
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), xyz)


def capsules_from_urdf(urdf_xml: str, link_names: Sequence[str]) -> list[Capsule]:
    """Enclosing capsules for the URDF ``<collision>`` primitives of some links.

    cylinder -> capsule on its axis, same radius; box -> capsule along its
    longest axis, radius = half-diagonal of the other two; sphere -> zero-length
    capsule; ``<capsule radius length>`` (non-standard, along z) -> itself.

    Parameters
    ----------
    urdf_xml : str
        URDF document.
    link_names : sequence of str
        Links to fit, each needing at least one primitive collision element.

    Returns
    -------
    list of Capsule
        Endpoints in the link frame (m). Named after the link when it has one
        primitive, else ``'<link>.<k>'`` in document order.

    Raises
    ------
    ConfigError
        A link is unknown, has no collision geometry, or uses a mesh.
    """
    root = ET.fromstring(urdf_xml)
    links = {link.get('name'): link for link in root.iter('link')}
    per_link: dict[str, list[tuple[str, ET.Element]]] = {}
    for name in link_names:
        key = f'collision.capsules.{name}'
        if name not in links:
            raise ConfigError(key, f'link {name!r} is not in the URDF')
        items = []
        for col in links[name].findall('collision'):
            geometry = col.find('geometry')
            kind = geometry[0].tag if geometry is not None and len(geometry) else 'none'
            if kind not in ('cylinder', 'box', 'sphere', 'capsule'):
                raise ConfigError(key, f'link {name!r} has {kind} collision geometry; '
                                       'give capsules for this link in the cell file')
            items.append((kind, col))
        if not items:
            raise ConfigError(key, f'link {name!r} has no collision geometry; '
                                   'give capsules for this link in the cell file')
        per_link[name] = items
    # urdfdom cannot load meshes we do not need nor parse <capsule> (it then drops
    # every collision of that link), so Pinocchio only sees the standard primitives.
    for link in root.iter('link'):
        for col in list(link.findall('collision')):
            geometry = col.find('geometry')
            if geometry is None or not len(geometry) or geometry[0].tag not in (
                    'cylinder', 'box', 'sphere'):
                link.remove(col)
        for vis in list(link.findall('visual')):
            link.remove(vis)
    clean = ET.tostring(root, encoding='unicode')
    model = pin.buildModelFromXML(clean)
    geom = pin.buildGeomFromUrdfString(model, clean, pin.GeometryType.COLLISION)
    capsules = []
    for name, items in per_link.items():
        frame = model.frames[model.getFrameId(name, pin.BODY)]
        from_pin = [o for o in geom.geometryObjects if model.frames[o.parentFrame].name == name]
        for k, (kind, col) in enumerate(items):
            cap_name = name if len(items) == 1 else f'{name}.{k}'
            if kind == 'capsule':
                g = col.find('geometry')[0]
                half = 0.5 * float(g.get('length'))
                capsules.append(_link_capsule(cap_name, name, _origin(col), half,
                                              float(g.get('radius'))))
            else:
                obj = from_pin.pop(0)
                # Pinocchio places geometry in the parent JOINT frame; the link frame
                # differs when fixed joints were merged into that joint.
                capsules.append(_fit(obj.geometry, cap_name, name,
                                     frame.placement.inverse() * obj.placement))
    return capsules
