"""Where the scanner is fixed: in the base frame (eye-on-base) or on a link of the arm (eye-on-arm, Eq. 8).

Owns the one difference the scanner's mount makes to a flange calibration.
A scanner fixed over the cell sees the flange from a pose ``T_base_cam``
that never changes: Eq. 9-12 fit the flange centres it sees to the robot's
flange positions in the base frame. A scanner fixed on a link of the arm
(the shoulder, the upper arm or the forearm: ``link1`` ... ``link3``, the
frame after that joint in the robot's DH table) moves with the joints before
it, and sees the flange moved by the joints after it. Eq. 8 with the mark the
flange centre::

    T_base_flange p = T_base_arm(q) T_arm_cam p_cam

so with ``p_arm = T_base_arm(q)^-1 T_base_flange p`` (the flange centre in the
link's frame at the joints ``q`` of the capture) ``T_arm_cam`` is the rigid
fit of Eq. 9-12 in the link's frame: the same pairs, Algorithm 1, e_icp
(with the verification pose in the link's frame) and quality gate as on the
base, only in another frame. Once calibrated, the scanner's pose at a
capture is ``T_base_arm(q) T_arm_cam`` with the joints of that capture.

``T_base_arm(q)`` is the robot's nominal forward kinematics of its first
joints, as the controller reports its own poses.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from celld.calib.kinematic import ArmModel, arm_of
from celld.config import SCANNER_MOUNTS
from celld.errors import InputError
from celld.robot import kinematics as kin
from celld.schemadoc import enum, matrix4, obj, vector
from celld.se3 import check_transform, invert

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ScannerMount:
    """The frame a scanner is fixed in, and the robot whose joints move it.

    Attributes
    ----------
    name : str
        One of :data:`celld.config.SCANNER_MOUNTS`.
    dh : kinematics.DH
        The robot's DH table (the controller's nominal one).
    """

    name: str = "base"
    dh: kin.DH = kin.UR10E

    def __post_init__(self) -> None:
        if self.name not in SCANNER_MOUNTS:
            raise InputError(f"scanner mount: expected one of {', '.join(SCANNER_MOUNTS)}, got {self.name!r}")

    @classmethod
    def of(cls, name: str, robot_model: str, table: kin.DH | None = None) -> ScannerMount:
        """The mount ``name`` on the robot model ``robot_model`` (a key of :data:`celld.robot.kinematics.MODELS`),
        whose controller computes with ``table`` (the model's published one when None).

        A scanner on the base does not move with the joints: its mount is
        the one base mount, whatever the robot, so that mounts compare by
        what they mean.
        """
        kin.model(robot_model)  # a model this project knows, on the base too
        return cls() if name == "base" else cls(name, table or kin.model(robot_model).dh)

    def dh_entry(self) -> dict[str, list[float]]:
        """The DH table as stored beside a scanner on the arm (read back by :func:`mount_from`)."""
        return kin.dh_as_dict(self.dh)

    @property
    def link(self) -> int:
        """The link the scanner is on: 0 for the base, else the joint after which its frame is."""
        return SCANNER_MOUNTS.index(self.name)

    @property
    def on_arm(self) -> bool:
        return self.link > 0

    @property
    def frame(self) -> str:
        """The name of the frame the scanner is fixed in, for reports and transform names."""
        return "base" if self.link == 0 else f"link{self.link}"

    def T_base_link(self, q: ArrayLike | None) -> Array:
        """The pose (4, 4) of the scanner's frame in the base frame at joints ``q`` (6,) rad.

        The identity for a base mount (``q`` may then be None).
        """
        if self.link == 0:
            return np.eye(4)
        if q is None:
            raise InputError(f"the scanner is on {self.frame}: its pose needs the robot's joints")
        qq = kin.check_q(q)
        return kin.matrix_from_rows(kin.forward_all_rows(qq.tolist(), self.dh)[self.link - 1])

    def to_link(self, T_base_x: ArrayLike, q: ArrayLike | None) -> Array:
        """A pose (4, 4) of the base frame in the scanner's frame at joints ``q``: ``T_link_x``."""
        T = check_transform(T_base_x, "T_base_x")
        return T if self.link == 0 else invert(self.T_base_link(q)) @ T

    def T_base_cam(self, T_link_cam: ArrayLike, q: ArrayLike | None) -> Array:
        """The scanner's pose in the base frame at joints ``q`` (Eq. 8), from its calibrated pose on its link."""
        T = check_transform(T_link_cam, "T_link_cam")
        return T if self.link == 0 else self.T_base_link(q) @ T


def _key(frame: str) -> str:
    return f"T_{frame}_cam"


def in_frame(report: Any, mount: ScannerMount) -> Any:
    """A solve's report with its transforms named in the mount's frame (``T_base_cam...`` -> ``T_link1_cam...``)."""
    if not mount.on_arm:
        return report
    old, new = _key("base"), _key(mount.frame)
    if isinstance(report, Mapping):
        return {(new + k[len(old) :] if k.startswith(old) else k): in_frame(v, mount) for k, v in report.items()}
    if isinstance(report, list):
        return [in_frame(v, mount) for v in report]
    return report


def in_any_frame(schema: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON Schema of what :func:`in_frame` makes of a report of shape ``schema``.

    Every ``T_base_cam...`` property (at any depth) is also allowed under each
    arm mount's frame (``T_link1_cam...``), and none of these is required:
    which one a report holds depends on its mount.
    """
    out: dict[str, Any] = dict(schema)
    old = _key("base")
    if "properties" in schema:
        props: dict[str, Any] = {}
        renamed: set[str] = set()
        for k, sub in schema["properties"].items():
            props[k] = in_any_frame(sub)
            if k.startswith(old):
                renamed.add(k)
                for frame in (ScannerMount(m).frame for m in SCANNER_MOUNTS[1:]):
                    props[_key(frame) + k[len(old) :]] = props[k]
        out["properties"] = props
        out["required"] = [r for r in schema.get("required", []) if r not in renamed]
    if "items" in schema:
        out["items"] = in_any_frame(schema["items"])
    if "oneOf" in schema:
        out["oneOf"] = [in_any_frame(b) for b in schema["oneOf"]]
    return out


def mount_entry(mount: ScannerMount, T_ref_cam: ArrayLike) -> dict[str, Any]:
    """A calibration's entries for the scanner's pose in its frame: ``T_base_cam``, or the mount, the robot's
    DH table and ``T_linkN_cam`` for a scanner on the arm (read back by :func:`placement_of`)."""
    T = check_transform(T_ref_cam, "T_ref_cam").tolist()
    if not mount.on_arm:
        return {_key("base"): T}
    return {"mount": mount.name, "dh": mount.dh_entry(), _key(mount.frame): T}


# The JSON shape of mount_entry's entries (properties to merge into a document's): none is required,
# which are there depends on the mount.
MOUNT_ENTRY_PROPERTIES: dict[str, dict[str, Any]] = {
    _key("base"): matrix4("The scanner's pose in the robot base frame (a scanner on the base)."),
    "mount": enum(SCANNER_MOUNTS, "Where the scanner is fixed (absent: the base)."),
    "dh": obj(
        "The robot's DH table the link frame is computed with (m, rad): its controller's (theta: its joint zeros; absent: zeros).",
        {k: vector(k, 6) for k in kin.DH._fields},
        ("d", "a", "alpha"),
    ),
    **{
        _key(ScannerMount(m).frame): matrix4(f"The scanner's pose in the frame of {m} (a scanner on the arm, Eq. 8).")
        for m in SCANNER_MOUNTS[1:]
    },
}


@dataclass(frozen=True)
class Placement:
    """A calibrated scanner: its mount and its pose in the mount's frame (``T_base_cam`` or ``T_linkN_cam``),
    and the arm's kinematic calibration when it has one (:mod:`celld.calib.kinematic`).

    With ``arm`` the base frame is the corrected arm's: ``T_ref_cam`` is the scanner's pose fitted with the
    arm, where the controller reports a pose the arm is at :meth:`modelled` of it, and a pose the arm is
    to reach is sent to the controller as :meth:`precorrect` of it. Without, both are the pose itself.
    """

    mount: ScannerMount
    T_ref_cam: Array
    arm: ArmModel | None = None

    def T_base_cam(self, q: ArrayLike | None) -> Array:
        """The scanner's pose in the base frame at joints ``q`` (any for a scanner on the base)."""
        return self.mount.T_base_cam(self.T_ref_cam, q)

    def modelled(self, T_reported: ArrayLike, q: ArrayLike | None) -> Array:
        """Where the calibrated arm is when the controller reports ``T_reported`` (the flange, or a frame fixed
        to it such as the TCP) with its joints at ``q``; the pose itself without an arm calibration."""
        T = check_transform(T_reported, "T_reported")
        if self.arm is None:
            return T
        if q is None:
            raise InputError("the arm's calibration corrects a reported pose by the joints it was reported at: none given")
        return self.arm.correction(q) @ T

    def precorrect(self, T_target: ArrayLike, q_near: ArrayLike, T_flange_frame: ArrayLike | None = None) -> Array:
        """The pose to send the controller so that the calibrated arm puts a frame fixed to the flange
        (``T_flange_frame``, the TCP; the flange itself by default) at ``T_target``, the joints nearest
        ``q_near``; ``T_target`` itself without an arm calibration.

        Raises
        ------
        InputError
            The target is out of the arm's reach.
        """
        T = check_transform(T_target, "T_target")
        if self.arm is None:
            return T
        T_ff = np.eye(4) if T_flange_frame is None else check_transform(T_flange_frame, "T_flange_frame")
        got = self.arm.precorrect(T @ invert(T_ff), q_near)
        if got is None:
            raise InputError(f"the pose {np.round(T[:3, 3], 4).tolist()} m is out of the calibrated arm's reach")
        return got[0] @ T_ff


def mount_from(doc: Mapping[str, Any], where: str) -> ScannerMount:
    """The mount a stored document names (``mount``, absent for the base) with its ``dh`` table.

    Raises
    ------
    InputError
        A mount this project does not know, or a missing or malformed DH table.
    """
    name = doc.get("mount", "base")
    if name not in SCANNER_MOUNTS:
        raise InputError(f"{where}.mount: expected one of {', '.join(SCANNER_MOUNTS)}, got {name!r}")
    if name == "base":
        return ScannerMount()
    try:
        return ScannerMount(name, kin.dh_from_dict(doc.get("dh"), f"{where}.dh"))
    except InputError as exc:
        raise InputError(
            f"{where}.dh: expected the robot's DH table (d, a, alpha and theta: 6 numbers each) for a scanner on {name}: {exc}"
        ) from exc


def placement_of(calibration: Mapping[str, Any], where: str = "calibration") -> Placement:
    """The :class:`Placement` of a stored calibration (:func:`mount_entry`'s entries).

    Raises
    ------
    InputError
        A mount this project does not know, a missing or malformed DH table or transform.
    """
    mount = mount_from(calibration, where)
    if "arm" in calibration:
        if mount.on_arm:
            raise InputError(f"{where}.arm: an arm calibration needs a fixed scanner, and this one is on {mount.name}")
        T_arm, arm = arm_of(calibration["arm"], f"{where}.arm")
        return Placement(mount, T_arm, arm)
    key = _key(mount.frame)
    try:
        T = check_transform(calibration.get(key, []), f"{where}.{key}")
    except (ValueError, TypeError) as exc:
        raise InputError(f"{where}.{key}: expected a 4x4 rigid transform: {exc}") from exc
    return Placement(mount, T)
