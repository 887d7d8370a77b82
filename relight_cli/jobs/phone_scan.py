"""A synthetic "phone scan" of a subject on the light stage (test data for ``relight
personalize``; URHand supp. 9's capture, known ground truth).

The subject — a hand.npz's shape and ``StageSettings.skin_seed``'s skin, rendered by the
stage's own renderer, so it is the same person as a capture made with those settings —
holds its hand still in a neutral pose under one environment map while a phone takes
``views`` photos from around it (rings above and below the hand, so the palm and the
back are both seen).  Per photo: the linear RGB render, its coverage mask, the camera,
and the joints projected into it with a detector's pixel noise, written in the 21-joint
MediaPipe layout (the finger metacarpal joints, which detectors do not give, are dropped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Scan:
    """``images`` [V] [H, W, 3] float32 linear, ``masks`` [V] [H, W] bool, ``cameras`` [V],
    ``keypoints`` (:class:`~relight_cli.formats.keypoints2d.Keypoints2D`), ``hand``: the
    subject posed as scanned (its true joints), ``env``: the stage-resampled map."""

    images: list
    masks: list
    cameras: list
    keypoints: object
    hand: object
    env: object


def scan_cameras(center: np.ndarray, views: int, radius: float, res: int, fov: float = 35.0):
    """``views`` look-at cameras around ``center``: alternating rings 35° above and 35°
    below it, azimuths spread evenly (the hand's +Z front and −Z back both covered)."""
    from relight_cli.formats.camera import Camera
    cams = []
    for i in range(views):
        azimuth = 2 * np.pi * (i + 0.5) / views
        elevation = np.radians(35.0 if i % 2 == 0 else -35.0)
        d = np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                      np.cos(elevation) * np.cos(azimuth)])
        cams.append(Camera.look_at(center + radius * d, center, [0.0, 1.0, 0.0], fov, res, res,
                                   f"phone{i:02d}"))
    return cams


def phone_scan(subject, settings, env, views: int = 8, res: int = 256, radius: float | None = None,
               pose: str = "relaxed", noise_px: float = 1.0, seed: int = 0) -> Scan:
    """Render the scan (see the module docstring).

    Args:
        subject: HandData of one hand (its shape; its frames are ignored).
        settings: the stage's :class:`~relight_cli.render.capture.StageSettings` (its
            ``skin_seed`` is the subject's skin; ``tex_res``, ``aa``, ``sss`` the look).
        env: the scan's EnvMap.  pose: a named pose (held still for every photo).
        noise_px: standard deviation of the keypoints' pixel noise.
        radius: the phone's distance from the hand's centre (metres); default: the whole
            hand inside the frame with a 15 % margin.
    """
    import copy

    from relight_cli.formats.keypoints2d import MEDIAPIPE_TO_WEBXR, Keypoints2D
    from relight_cli.hand.poses import named_pose
    from relight_cli.hand.skinning import posed_joints
    from relight_cli.render.appearance import hand_materials
    from relight_cli.render.capture import FrameRenderer, plan_capture, stage_envmap

    hand = copy.deepcopy(subject)
    hand.hands = hand.hands[:1]
    hand.hands[0].poses = named_pose(pose, hand.side, hand.rest_joints)[None].astype(np.float64)
    hand.hands[0].translations = np.zeros((1, 3))
    hand.mean_texture = None
    joints = posed_joints(hand.hands[0].poses, hand.hands[0].translations, hand.rest_joints,
                          hand.parents)[0]
    if not np.allclose(hand.hands[0].root, np.eye(4)):
        joints = joints @ hand.hands[0].root[:3, :3].T + hand.hands[0].root[:3, 3]
    from relight_cli.hand.scene import posed_meshes
    vertices = np.concatenate([m.vertices for m in posed_meshes(hand, 0, "coarse")])
    center = 0.5 * (vertices.min(0) + vertices.max(0))
    if radius is None:                  # the bounding sphere inside the 35° field of view
        reach = float(np.linalg.norm(vertices - center, axis=1).max())
        radius = 1.15 * reach / np.sin(np.radians(35.0) / 2)
    cameras = scan_cameras(center, views, radius, res)
    stage_env = stage_envmap(env, settings.eval_env_res)
    plan = plan_capture(hand, settings, motion=hand)
    materials = hand_materials(plan.motion, "fine", max(settings.tex_res, 256), settings.skin_seed)
    renderer = FrameRenderer(plan, materials, settings)
    rng = np.random.default_rng(seed)
    images, masks, uv = [], [], []
    for cam, result in renderer.env_views(hand, 0, stage_env, cameras):
        images.append(np.asarray(result.image, np.float32))
        masks.append(np.asarray(result.mask) > 0.5)
        x = joints @ np.asarray(cam.R).T + np.asarray(cam.t)
        p = x[:, :2] / x[:, 2:] @ np.asarray(cam.K)[:2, :2].T + np.asarray(cam.K)[:2, 2]
        uv.append(p + rng.normal(0.0, noise_px, p.shape))
    uv = np.asarray(uv)
    conf = np.zeros(uv.shape[:2])
    conf[:, MEDIAPIPE_TO_WEBXR] = 1.0
    uv[conf == 0] = 0.0
    names = [f"view_{i:02d}.exr" for i in range(views)]
    kp = Keypoints2D(names, uv, conf, np.zeros(views, np.int64), "mediapipe-21", hand.side)
    return Scan(images, masks, cameras, kp, hand, stage_env)


def write_scan(folder: str, scan: Scan, provenance=None) -> list:
    """Write ``scan`` into ``folder`` (created; each file atomic): ``view_NN.exr`` (RGBA,
    linear, A the coverage mask), ``cameras.json`` (one relight/camera per view, in
    order), ``keypoints.json`` (relight/keypoints-2d).  ``provenance``: callable(format,
    version) → the record each file carries, or None.  Returns the paths written."""
    import os

    from relight_cli.formats import camera as cameras_json
    from relight_cli.formats import keypoints2d as K
    from relight_cli.formats.exr import write_exr

    def record(fmt, version):
        return None if provenance is None else provenance(fmt, version)
    os.makedirs(folder, exist_ok=True)
    written = []
    for name, image, mask in zip(scan.keypoints.images, scan.images, scan.masks):
        path = os.path.join(folder, name)
        a = mask.astype(np.float32)
        write_exr(path, {"R": image[..., 0] * a, "G": image[..., 1] * a, "B": image[..., 2] * a,
                         "A": a}, provenance=record("relight/render", 1))
        written.append(path)
    cams = os.path.join(folder, "cameras.json")
    cameras_json.write_cameras(cams, scan.cameras,
                               record(cameras_json.FORMAT, cameras_json.VERSION))
    kp = os.path.join(folder, "keypoints.json")
    K.write_keypoints2d(kp, scan.keypoints, record(K.FORMAT, K.VERSION))
    return written + [cams, kp]
