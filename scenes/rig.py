"""MuJoCo model of the tapping rig: the GelTip on a 3D printer with two servos.

World frame: the printer bed, Z up, metres. The printer head moves on three prismatic
axes (``printer_x``, ``printer_y``, ``printer_z``) and carries an indenter on a pitch
servo (``indenter_pitch``, about world +Y); the sensor lies on the bed with its axis along
world +X and rolls on a servo (``sensor_roll``, about its own axis). Every joint, actuator,
body, geom, site and camera is named in the XML and looked up by name.

The membrane is geometric, as in the published set-up: the indenter passes into it and the
in-sensor depth camera ``geltip_depth`` sees whichever surface is nearer. MuJoCo culls back
faces, so the camera sees an inward-facing copy of the membrane (``membrane_view``, group
0) while the overview sees the outward one (``membrane``, group 2).

One model carries every indenter of a session (``indenter_<name>`` geoms on the servo,
tip sites ``indenter_tip_<name>``); mounting one moves its geom into the visible group
and the others into a spare group, so swapping objects costs no recompilation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .body import sensor_body
from .camera import Camera, lens_resample, unseen
from .geometry import membrane_mesh
from .kinematics import PITCH_TRAVEL_RAD, ROLL_TRAVEL_RAD, SENSOR_TO_WORLD_AT_ROLL0, RigLayout, tap_pose
from .taps import Tap
from .spec import SensorSpec

#: Geom groups: what the in-sensor depth camera sees, and visual-only parts.
GROUP_MEMBRANE_VIEW, GROUP_INDENTER, GROUP_MEMBRANE, GROUP_BODY, GROUP_SPARE = 0, 1, 2, 3, 4
DEPTH_GROUPS = (GROUP_MEMBRANE_VIEW, GROUP_INDENTER)
#: Multisampling of the depth camera's buffer: none. Depth is read at pixel centres
#: either way, and on the software renderer 4 samples cost a quarter of a capture.
DEPTH_SAMPLES = 0

#: Model extent for MuJoCo's near/far planes, which are fractions of it (metres).
EXTENT_M = 0.5
#: Near and far clip planes of every camera, metres (set explicitly: MuJoCo's defaults,
#: fractions of the model extent, can clip a small sensor).
ZNEAR_M, ZFAR_M = 0.001, 2.0


def _f(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.atleast_1d(values))


def _stl(mesh: trimesh.Trimesh) -> bytes:
    return mesh.export(file_type="stl")


@dataclass(frozen=True)
class RigScene:
    """An MJCF document and the mesh files it refers to (file name -> STL bytes)."""

    xml: str
    assets: dict[str, bytes]
    indenters: tuple[str, ...]
    #: name -> (V, 3) the indenter mesh's vertices in its own frame, metres.
    vertices: dict[str, np.ndarray]

    def export(self, folder: str | Path) -> Path:
        """Write ``rig.xml`` and its meshes, for ``python -m mujoco.viewer --mjcf``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in self.assets.items():
            (folder / name).write_bytes(data)
        path = folder / "rig.xml"
        path.write_text(self.xml)
        return path


def _safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _check_clip(membrane: trimesh.Trimesh, camera: Camera, name: str) -> None:
    """Refuse a membrane whose part in the camera's view lies outside the depth camera's
    clip planes (ZNEAR_M, ZFAR_M): the depth map would lose it."""
    out, hidden = unseen(membrane, camera)
    seen = ~(out | hidden)
    z = np.asarray(membrane.vertices)[seen, 2]
    if len(z) and (z.min() <= ZNEAR_M or z.max() >= ZFAR_M):
        raise ValueError(f"sensor {name!r}: the membrane in view spans z {z.min() * 1e3:.2f} to {z.max() * 1e3:.1f} mm "
                         f"from the camera, outside the depth camera's clip planes ({ZNEAR_M * 1e3:g} to "
                         f"{ZFAR_M * 1e3:g} mm)")


def rig_scene(
    spec: SensorSpec,
    indenters: dict[str, trimesh.Trimesh],
    membrane: trimesh.Trimesh | None = None,
    layout: RigLayout = RigLayout(),
) -> RigScene:
    """Build the rig's MJCF from a sensor spec, a membrane mesh and indenter meshes.

    Parameters
    ----------
    indenters : name -> watertight mesh in metres, its feature along local +z (see
        ``scenes.indenters``); each is mounted pointing down at pitch 0. The first is
        mounted when the model loads.
    membrane : the membrane in the sensor (camera) frame; default: built from the spec.
    """
    if not indenters:
        raise ValueError("indenters must name at least one indenter mesh")
    membrane = membrane_mesh(spec) if membrane is None else membrane
    body = sensor_body(spec, membrane)  # the glass core under the membrane, checked
    _check_clip(membrane, Camera.from_spec(spec), spec.name)
    inward = membrane.copy()
    inward.invert()
    cam = spec.camera
    lo, hi = membrane.bounds
    base_z = float(lo[2])
    radius = float(np.max(np.linalg.norm(membrane.vertices[:, :2], axis=1)))
    to_world = np.eye(4)
    to_world[:3, :3] = SENSOR_TO_WORLD_AT_ROLL0
    sensor_quat = trimesh.transformations.quaternion_from_matrix(to_world)  # (w, x, y, z), as MuJoCo
    names = {name: _safe_name(name) for name in indenters}
    if len(set(names.values())) != len(names):
        raise ValueError(f"indenter names must stay distinct as file names, got {sorted(indenters)}")
    assets = {"membrane.stl": _stl(membrane), "membrane_view.stl": _stl(inward), "glass_core.stl": _stl(body.core)}
    mesh_xml, geom_xml = [], []
    for i, (name, mesh) in enumerate(indenters.items()):
        safe = names[name]
        assets[f"indenter_{safe}.stl"] = _stl(mesh)
        mesh_xml.append(f'<mesh name="indenter_{safe}" file="indenter_{safe}.stl"/>')
        group = GROUP_INDENTER if i == 0 else GROUP_SPARE
        geom_xml.append(
            f'<geom name="indenter_{safe}" type="mesh" mesh="indenter_{safe}" group="{group}" '
            f'rgba="0.85 0.45 0.2 1" mass="0.01"/>\n'
            f'              <site name="indenter_tip_{safe}" pos="0 0 {_f(mesh.bounds[1, 2])}" size="0.0005" group="5"/>'
        )
    mesh_xml = "\n    ".join(mesh_xml)
    geom_xml = "\n              ".join(geom_xml)
    # MuJoCo's camera is a centred pinhole: it renders the lens' cover (RigModel.depth)
    cover = Camera.from_spec(spec).pinhole_cover()
    fovy_deg = math.degrees(2 * math.atan((cover.height / 2) / cover.f))
    xml = f"""<mujoco model="geltip_tapping_rig">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002"/>
  <statistic center="{_f(layout.sensor_origin)}" extent="{EXTENT_M}"/>
  <visual>
    <map znear="{ZNEAR_M / EXTENT_M:.9g}" zfar="{ZFAR_M / EXTENT_M:.9g}"/>
    <global offwidth="{max(cam.width, 1280)}" offheight="{max(cam.height, 960)}"/>
    <quality shadowsize="2048"/>
  </visual>
  <default>
    <geom contype="0" conaffinity="0"/>
    <default class="frame"><geom type="box" group="{GROUP_BODY}" rgba="0.15 0.15 0.17 1"/></default>
  </default>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.8 0.8 0.8" rgb2="0.7 0.7 0.72" width="256" height="256"/>
    <material name="bed" texture="grid" texrepeat="8 8"/>
    <mesh name="membrane" file="membrane.stl" inertia="shell"/>
    <mesh name="membrane_view" file="membrane_view.stl" inertia="shell"/>
    <mesh name="glass_core" file="glass_core.stl" inertia="shell"/>
    {mesh_xml}
  </asset>
  <worldbody>
    <light name="key" pos="0.1 -0.4 0.8" dir="0 0.4 -0.8" diffuse="0.8 0.8 0.8"/>
    <light name="fill" pos="0.4 0.4 0.6" dir="-0.3 -0.3 -0.6" diffuse="0.4 0.4 0.4"/>
    <camera name="overview" mode="targetbody" target="sensor" pos="{_f(np.add(layout.sensor_origin, (-0.07, -0.15, 0.09)))}" fovy="45"/>
    <geom name="printer_bed" type="box" size="0.2 0.2 0.004" pos="{_f((layout.sensor_origin[0], 0, 0))}" material="bed" group="{GROUP_BODY}"/>
    <geom name="frame_left" class="frame" size="0.012 0.012 0.25" pos="{_f((layout.sensor_origin[0], -0.22, 0.25))}"/>
    <geom name="frame_right" class="frame" size="0.012 0.012 0.25" pos="{_f((layout.sensor_origin[0], 0.22, 0.25))}"/>
    <geom name="frame_top" class="frame" size="0.012 0.232 0.012" pos="{_f((layout.sensor_origin[0], 0, 0.5))}"/>
    <geom name="sensor_holder" class="frame" size="0.02 0.02 {layout.sensor_origin[2] / 2 - 0.002:.9g}" pos="{_f((layout.sensor_origin[0] + base_z - 0.02, 0, layout.sensor_origin[2] / 2))}"/>
    <body name="sensor" pos="{_f(layout.sensor_origin)}" quat="{_f(sensor_quat)}">
      <joint name="sensor_roll" type="hinge" axis="0 0 1" range="{_f(ROLL_TRAVEL_RAD)}" damping="0.05"/>
      <inertial pos="0 0 0" mass="0.05" diaginertia="1e-5 1e-5 1e-5"/>
      <camera name="geltip_depth" pos="0 0 0" xyaxes="1 0 0 0 -1 0" fovy="{fovy_deg:.9g}"/>
      <geom name="membrane_view" type="mesh" mesh="membrane_view" group="{GROUP_MEMBRANE_VIEW}" rgba="0.9 0.9 0.9 1" mass="0"/>
      <geom name="membrane" type="mesh" mesh="membrane" group="{GROUP_MEMBRANE}" rgba="0.75 0.75 0.78 1" mass="0"/>
      <geom name="glass_core" type="mesh" mesh="glass_core" group="{GROUP_BODY}" rgba="0.7 0.85 1 0.35" mass="0"/>
      <geom name="sensor_body" type="cylinder" size="{radius + 0.002:.9g} 0.015" pos="0 0 {base_z - 0.015:.9g}" group="{GROUP_BODY}" rgba="0.1 0.1 0.1 1" mass="0"/>
    </body>
    <body name="gantry_x">
      <joint name="printer_x" type="slide" axis="1 0 0" range="{_f(layout.travel_x)}" damping="50"/>
      <inertial pos="0 0 0" mass="1" diaginertia="1e-3 1e-3 1e-3"/>
      <body name="gantry_y">
        <joint name="printer_y" type="slide" axis="0 1 0" range="{_f(layout.travel_y)}" damping="50"/>
        <inertial pos="0 0 0" mass="1" diaginertia="1e-3 1e-3 1e-3"/>
        <body name="printer_head">
          <joint name="printer_z" type="slide" axis="0 0 1" range="{_f(layout.travel_z)}" damping="50"/>
          <inertial pos="0 0 0" mass="0.5" diaginertia="1e-3 1e-3 1e-3"/>
          <geom name="head" type="box" size="0.025 0.02 0.015" group="{GROUP_BODY}" rgba="0.2 0.2 0.22 1"/>
          <geom name="indenter_mount" type="box" size="0.006 0.012 {layout.mount_length / 2:.9g}" pos="0 0 {-layout.mount_length / 2:.9g}" group="{GROUP_BODY}" rgba="0.3 0.3 0.35 1"/>
          <body name="indenter_servo" pos="0 0 {-layout.mount_length:.9g}">
            <joint name="indenter_pitch" type="hinge" axis="0 1 0" range="{_f(PITCH_TRAVEL_RAD)}" damping="0.05"/>
            <inertial pos="0 0 0" mass="0.05" diaginertia="1e-5 1e-5 1e-5"/>
            <geom name="servo_horn" type="cylinder" size="0.01 0.008" quat="0.7071068 0.7071068 0 0" group="{GROUP_BODY}" rgba="0.05 0.05 0.05 1"/>
            <body name="indenter" pos="0 0 {-layout.indenter_offset:.9g}" quat="0 1 0 0">
              {geom_xml}
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position name="printer_x" joint="printer_x" kp="2000" ctrlrange="{_f(layout.travel_x)}"/>
    <position name="printer_y" joint="printer_y" kp="2000" ctrlrange="{_f(layout.travel_y)}"/>
    <position name="printer_z" joint="printer_z" kp="2000" ctrlrange="{_f(layout.travel_z)}"/>
    <position name="indenter_pitch" joint="indenter_pitch" kp="2" ctrlrange="{_f(PITCH_TRAVEL_RAD)}"/>
    <position name="sensor_roll" joint="sensor_roll" kp="2" ctrlrange="{_f(ROLL_TRAVEL_RAD)}"/>
  </actuator>
</mujoco>
"""
    vertices = {name: np.array(mesh.vertices, dtype=np.float64) for name, mesh in indenters.items()}
    return RigScene(xml, assets, tuple(indenters), vertices)


class Rig:
    """A compiled rig: MuJoCo model and data, with tap poses and depth capture."""

    def __init__(self, scene: RigScene, spec: SensorSpec, layout: RigLayout = RigLayout()):
        from .gl import import_mujoco

        self.mujoco = import_mujoco()
        self.spec = spec
        self._lens = Camera.from_spec(spec)
        self._cover = self._lens.pinhole_cover()
        self.layout = layout
        self.scene = scene
        self.model = self.mujoco.MjModel.from_xml_string(scene.xml, assets=scene.assets)
        self.data = self.mujoco.MjData(self.model)
        self.home()
        self.mounted: str | None = None
        self.mount(scene.indenters[0])
        self._renderers: dict = {}
        self._membrane_depth: np.ndarray | None = None  # the pinhole cover's, rendered once

    # -- indenters --------------------------------------------------------------------

    def mount(self, name: str) -> None:
        """Mount one of the model's indenters (the others go to a hidden group)."""
        if name not in self.scene.indenters:
            raise ValueError(f"indenter {name!r} is not in this rig; it has {list(self.scene.indenters)}")
        if name == self.mounted:
            return
        for other in self.scene.indenters:
            geom = self.model.geom(f"indenter_{_safe_name(other)}")
            self.model.geom_group[geom.id] = GROUP_INDENTER if other == name else GROUP_SPARE
        self.mounted = name

    # -- poses ------------------------------------------------------------------------

    def qpos(self, joint: str) -> float:
        return float(self.data.joint(joint).qpos[0])

    def set_joints(self, **values: float) -> None:
        """Set joint positions by name (a settled servo or axis) and update kinematics."""
        for name, value in values.items():
            joint = self.model.joint(name)
            lo, hi = self.model.jnt_range[joint.id]
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise ValueError(f"{name} = {value:.6g} is outside its travel [{lo:.6g}, {hi:.6g}]")
            self.data.joint(name).qpos[0] = value
            self.data.actuator(name).ctrl[0] = value
        self.mujoco.mj_kinematics(self.model, self.data)
        self.mujoco.mj_camlight(self.model, self.data)  # cameras are not part of kinematics

    def home(self) -> None:
        x, y, z = self.layout.home
        self.set_joints(printer_x=x, printer_y=y, printer_z=z, indenter_pitch=0.0, sensor_roll=0.0)

    def sensor_to_world(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t): the sensor frame's rotation and origin in the world, now."""
        body = self.data.body("sensor")
        return np.array(body.xmat).reshape(3, 3), np.array(body.xpos)

    def tap_pose(self, tap: Tap) -> dict[str, float]:
        """Joint positions that press the indenter ``tap.depth`` into the membrane
        (``scenes.kinematics.tap_pose``); ValueError when the head cannot reach them."""
        if tap.object not in self.scene.indenters:
            raise ValueError(f"tap {tap.index} presses {tap.object!r}, which is not in this rig; it has "
                             f"{list(self.scene.indenters)}")
        pose = tap_pose(tap, self.scene.vertices[tap.object], self.layout)
        for name in ("printer_x", "printer_y", "printer_z"):
            lo, hi = self.model.jnt_range[self.model.joint(name).id]
            if not lo <= pose[name] <= hi:
                raise ValueError(
                    f"tap {tap.index} ({tap.object}, row {tap.row}, position {tap.position}) needs "
                    f"{name} = {pose[name]:.4f} m, outside the printer's travel [{lo:.3f}, {hi:.3f}]"
                )
        return pose

    def press(self, tap: Tap) -> None:
        self.mount(tap.object)
        self.set_joints(**self.tap_pose(tap))

    # -- rendering --------------------------------------------------------------------

    def _renderer(self, width: int, height: int, samples: int | None = None):
        """A renderer of this size; ``samples``: its buffer's multisampling (None: the
        model's, MuJoCo's 4)."""
        key = (width, height, samples)
        if key not in self._renderers:
            quality = self.model.vis.quality
            kept = quality.offsamples
            if samples is not None:
                quality.offsamples = samples  # read when the context is made
            try:
                self._renderers[key] = self.mujoco.Renderer(self.model, height, width)
            except Exception as exc:  # MuJoCo raises plain Exceptions for GL failures
                from .gl import GLPlatformError, missing_message

                raise GLPlatformError(f"MuJoCo could not open a rendering context: {exc}; {missing_message()}") from exc
            finally:
                quality.offsamples = kept
        return self._renderers[key]

    def _depth_of(self, groups) -> np.ndarray:
        """The depth camera's (pinhole cover's) z-depth of these geom groups, (H, W)
        float32 metres; the far plane where none is seen."""
        cam = self.spec.camera
        renderer = self._renderer(cam.width, cam.height, DEPTH_SAMPLES)
        option = self.mujoco.MjvOption()
        option.geomgroup[:] = 0
        option.sitegroup[:] = 0  # sites would stand out of the indenter's surface
        for group in groups:
            option.geomgroup[group] = 1
        renderer.enable_depth_rendering()
        self._effects(renderer, False)  # shadows and reflections only cost time in depth
        renderer.update_scene(self.data, camera="geltip_depth", scene_option=option)
        return np.asarray(renderer.render(), dtype=np.float32)

    def depth(self) -> np.ndarray:
        """Depth map of the in-sensor camera: (H, W) float32, metres, planar z.

        The membrane does not move in the camera's view, so its depth is rendered once;
        each capture renders the mounted indenter alone and keeps the nearer of the two
        at each pixel, as one render of both would (the z-buffer's test).
        """
        if self._membrane_depth is None:
            self._membrane_depth = self._depth_of([g for g in DEPTH_GROUPS if g != GROUP_INDENTER])
        depth = np.minimum(self._membrane_depth, self._depth_of([GROUP_INDENTER]))
        # the pinhole's z-depth read where each of the lens' rays lands: z is the same
        # point's, whichever camera saw it
        return depth if self._cover is self._lens else lens_resample(depth, self._lens, self._cover)

    def _effects(self, renderer, on: bool) -> None:
        flags = self.mujoco.mjtRndFlag
        for flag in (flags.mjRND_SHADOW, flags.mjRND_REFLECTION, flags.mjRND_SKYBOX):
            renderer.scene.flags[flag] = on

    def snapshot(self, width: int = 1280, height: int = 960, camera: str = "overview") -> np.ndarray:
        """RGB overview of the rig: (H, W, 3) float32 in [0, 1]."""
        renderer = self._renderer(width, height)
        renderer.disable_depth_rendering()
        self._effects(renderer, True)
        option = self.mujoco.MjvOption()
        option.geomgroup[:] = 1
        option.geomgroup[GROUP_MEMBRANE_VIEW] = 0
        option.geomgroup[GROUP_SPARE] = 0
        renderer.update_scene(self.data, camera=camera, scene_option=option)
        return renderer.render().astype(np.float32) / 255.0

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()


def tap_depths(spec: SensorSpec, taps, membrane: trimesh.Trimesh | None = None):
    """Press each tap on a rig carrying its objects and capture the depth maps.

    Yields (D_ref, None) first (the no-contact capture), then (depth, tap) per tap: (H, W)
    float32 metres, planar z. The rig is closed when the generator is.
    """
    from .indenters import indenter

    taps = list(taps)
    membrane = membrane_mesh(spec) if membrane is None else membrane
    objects = sorted({t.object for t in taps}) or ["sphere"]
    rig = Rig(rig_scene(spec, {name: indenter(name) for name in objects}, membrane=membrane), spec)
    try:
        rig.home()
        yield rig.depth(), None
        for tap in taps:
            rig.press(tap)
            yield rig.depth(), tap
    finally:
        rig.close()
