"""Rigid poses from FAP values: jaw, eyeballs, tongue and head, as (4, 4) rest -> now matrices.

- head (48-50): rotation about feature point 7.1, R = Ry(yaw) Rx(pitch) Rz(roll), applied to
  everything (the skin is simulated in the head's frame, then carried by this pose);
- jaw (3, 14, 15 through calibrated controls): rotation about the hinge (jaw_pivot,
  jaw_axis) by the opening angle while the condyles glide forward and down the articular
  eminence (`CONDYLE_GLIDE` metres per radian of opening, `EMINENCE_SLOPE` below the
  horizontal), then translation (thrust along +z, shift along x). Without the glide the
  bottom of the chin (2.1), 11 cm below and 5 cm in front of the hinge on the generic
  head, moved down at most 10 mm (at 0.42 rad) and then back up: open_jaw could not reach
  half its range, and a wider opening raised the chin again;
- eyeballs (23-28): yaw about +y and pitch about +x through the eye centre, then thrust
  along +z (ES units); pupils (29-30) have no mesh of their own: their dilation is
  reported as a scale factor of the pupil diameter (1 + v IRISD / (IRISD0 / 3));
- tongue (43-47, carried by the jaw): 43 shifts and 45 thrusts it (MW), 46 raises it
  (MNS), 44 raises the tip by pitching it about its root, 47 rolls it, approximated by
  narrowing it (x scale cos(angle)) around 6.2 (a rigid part cannot curl).
"""

from __future__ import annotations

import numpy as np

from fae.linalg import axis_angle
from fae.mpeg4.faps import AU

CONDYLE_GLIDE = 0.025  # metres of condylar translation per radian of opening
EMINENCE_SLOPE = np.radians(35.0)  # the glide's angle below the forward (+z) direction


def rotation_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rotation_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rotation_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def about(R: np.ndarray, center: np.ndarray, translation: np.ndarray | None = None) -> np.ndarray:
    """(4, 4): rotate by R (3, 3) about `center` (3,), then translate."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center - R @ center + (0.0 if translation is None else translation)
    return T


class RigidRig:
    """Rest data of a head's rigid parts, precomputed once; `poses(values, jaw)` per frame."""

    def __init__(self, face, fapu: dict[str, float]):
        self.fapu = fapu
        fp = face.feature_point_positions()
        V = np.asarray(face.skin_vertices)
        self.head_center = fp.get("7.1", np.array([0.0, V[:, 1].min(), V[:, 2].mean()]))
        self.jaw_pivot = np.asarray(face.jaw_pivot, dtype=np.float64)
        self.jaw_axis = np.asarray(face.jaw_axis, dtype=np.float64) / np.linalg.norm(face.jaw_axis)
        self.eye_centers = {k: np.asarray(v, dtype=np.float64) for k, v in face.eye_centers.items()}
        tongue = face.parts.get("tongue")
        tv = np.asarray(tongue.vertices) if tongue is not None else np.zeros((1, 3))
        self.tongue_tip = fp.get("6.1", tv[np.argmax(tv[:, 2])])
        self.tongue_center = fp.get("6.2", tv.mean(axis=0))
        self.tongue_root = np.array([self.tongue_center[0], self.tongue_center[1], tv[:, 2].min()])
        self.tongue_length = max(float(np.linalg.norm(self.tongue_tip - self.tongue_root)), 1e-3)
        self.irisd0 = fapu["IRISD"] * 1024.0
        # (key, value) of the last call, one attribute each: replaced whole, so threads sharing
        # a rig (calibration's settles) never read one call's key with another's value
        self._jaw_cache: tuple | None = None
        self._poses_cache: tuple | None = None

    def jaw(self, angle: float, thrust: float, shift: float) -> np.ndarray:
        """(4, 4) jaw pose: opening `angle` rad about the hinge with the condylar glide, then
        `thrust` (+z) and `shift` (+x) metres (the caller must not modify it)."""
        key = (float(angle), float(thrust), float(shift))
        cached = self._jaw_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        pose = self._jaw_pose(*key)
        pose.setflags(write=False)
        self._jaw_cache = (key, pose)
        return pose

    def _jaw_pose(self, angle: float, thrust: float, shift: float) -> np.ndarray:
        glide = CONDYLE_GLIDE * max(float(angle), 0.0)
        move = np.array([shift, -glide * np.sin(EMINENCE_SLOPE), thrust + glide * np.cos(EMINENCE_SLOPE)])
        return about(axis_angle(self.jaw_axis, angle), self.jaw_pivot, move)

    def head(self, v: np.ndarray) -> np.ndarray:
        R = rotation_y(v[48] * AU) @ rotation_x(v[47] * AU) @ rotation_z(v[49] * AU)
        return about(R, self.head_center)

    def eye(self, v: np.ndarray, side: str) -> np.ndarray:
        """(4, 4) the eyeball's own pose (the identity for a head without that eye)."""
        if side not in self.eye_centers:
            return np.eye(4)
        k = 0 if side == "eye_l" else 1
        R = rotation_y(v[22 + k] * AU) @ rotation_x(v[24 + k] * AU)
        return about(R, self.eye_centers[side], np.array([0.0, 0.0, v[26 + k] * self.fapu["ES"]]))

    def tongue(self, v: np.ndarray) -> np.ndarray:
        pitch = -np.arcsin(np.clip(v[43] * self.fapu["MNS"] / self.tongue_length, -1.0, 1.0))
        T = about(rotation_x(pitch), self.tongue_root)
        roll = np.eye(4)
        roll[0, 0] = np.cos(v[46] * AU)
        roll[0, 3] = self.tongue_center[0] * (1.0 - roll[0, 0])
        move = np.eye(4)
        move[:3, 3] = [-v[42] * self.fapu["MW"], v[45] * self.fapu["MNS"], v[44] * self.fapu["MW"]]
        return move @ T @ roll

    def pupil_scale(self, v: np.ndarray) -> dict[str, float]:
        d = self.irisd0 / 3.0
        return {"eye_l": max(0.05, 1.0 + v[28] * self.fapu["IRISD"] / d),
                "eye_r": max(0.05, 1.0 + v[29] * self.fapu["IRISD"] / d)}

    def poses(self, v: np.ndarray, jaw: np.ndarray) -> dict[str, np.ndarray]:
        """Bone name -> (4, 4) rest -> now for FAP values v (68,) and jaw pose (4, 4) in the head
        frame (the caller must not modify them). Held poses (most frames of a stream move only
        the face) are not recomputed."""
        key = v[22:30].tobytes() + v[42:50].tobytes() + np.asarray(jaw).tobytes()
        cached = self._poses_cache
        if cached is not None and cached[0] == key:
            return dict(cached[1])
        poses = self._all_poses(v, jaw)
        for T in poses.values():
            T.setflags(write=False)
        self._poses_cache = (key, poses)
        return dict(poses)

    def _all_poses(self, v: np.ndarray, jaw: np.ndarray) -> dict[str, np.ndarray]:
        H = self.head(v)
        return {"head": H, "jaw": H @ jaw, "eye_l": H @ self.eye(v, "eye_l"), "eye_r": H @ self.eye(v, "eye_r"),
                "tongue": H @ jaw @ self.tongue(v)}
