"""The scale from the ball's apparent size (``--object-size-m``) on a ball drifting in depth.

A pinhole camera films a bouncing ball moving away from it at a steady speed; the tracker's
sizes are exact except in a run of frames where the ball crosses a background of its own grey
and looks 25% smaller (as measured on the camera section's clips, docs/camera-footage.md). The
camera read from the sizes must follow the true depth and map heights without a drift.
"""

import numpy as np

from sysid_bench.core.footage import BallTrack, camera_for

F_PX, CX, CY, H, W = 520.0, 5.0, 0.6, 360, 640  # focal length, where the camera looks, frame
D = 0.07  # the ball's diameter, m


def _filmed(shrunk=slice(30, 45)):
    # a ball dropped from 1.2 m bouncing with e = 0.8, moving 0.3 m/s sideways (fine steps)
    y, vy, ys = 1.2, 0.0, []
    for k in range(50 * 200):
        if k % 200 == 0:
            ys.append(y)
        vy -= 9.81 * 2.5e-4
        y += vy * 2.5e-4
        if y < 0:
            y, vy = -y, -0.8 * vy
    xy = np.column_stack([4.8 + 0.3 * 0.05 * np.arange(50), ys])  # (T, 2), floor 0
    z = 2.8 + 0.12 * 0.05 * np.arange(50)  # 12 cm/s away from the camera
    pix = np.column_stack([W / 2 + F_PX * (xy[:, 0] - CX) / z,
                           H / 2 - F_PX * (xy[:, 1] - CY) / z])
    radii = 0.5 * D * F_PX / z
    radii[shrunk] *= 0.75
    trk = BallTrack(pixels=pix, radius=float(np.median(radii)), found=np.ones(50, bool),
                    radii=radii)
    return trk, xy, F_PX / z


def test_scale_follows_the_depth_through_a_run_of_bad_sizes():
    trk, _, true_scale = _filmed()
    cam = camera_for("ball", trk, (H, W), object_size_m=D)
    err = cam.scales(50) / true_scale - 1
    assert np.max(np.abs(err)) < 0.005, err
    # the uncertainty: a pixel on the 12-13 px diameter
    assert 0.07 < cam.scale_rel_std < 0.09


def test_heights_scaled_about_the_picture_centre_have_no_drift():
    trk, xy, _ = _filmed(shrunk=slice(0, 0))
    cam = camera_for("ball", trk, (H, W), object_size_m=D)
    pos = cam.to_metres(trk.pixels)
    dy = pos[:, 1] - xy[:, 1]
    assert np.max(np.abs(dy)) < 0.005, dy  # the floor at 0 within 5 mm, no drift with depth
    dx = pos[:, 0] - xy[:, 0]
    assert np.ptp(dx) < 0.002, dx  # x up to a constant (no walls in view)
