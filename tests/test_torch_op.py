"""The PyTorch op (issue 15): ``autoalign.torch.silhouettes`` against torch's gradcheck and against
central finite differences of its own forward pass, with 4x4 and kornia ``Se3`` poses, and a
``torch.optim`` loop that fits a pose with it.

Scenes: procedural meshes in views around them (small images, to keep the finite differences cheap).
"""

from __future__ import annotations

import kornia.geometry.liegroup as kornia_liegroup  # noqa: E402 - installed by the test command: never skipped
import numpy as np
import pytest
import torch  # noqa: E402

from autoalign.experiments.scenes.procedural_models import procedural_models  # noqa: E402
from autoalign.experiments.scenes.synthetic import (  # noqa: E402
    default_K,
    random_rotation,
    ring_cameras,
)
from autoalign.geometry.mesh import mesh_from_trimesh  # noqa: E402
from autoalign.geometry.se3 import make_pose  # noqa: E402
from autoalign.rasterizers.soft_silhouette import SoftSilhouetteRasterizer  # noqa: E402
from autoalign.torch import SilhouetteLoss, silhouette_loss, silhouettes  # noqa: E402

POOL = {pm.name: pm for pm in procedural_models()}


def mesh(name: str):
    return mesh_from_trimesh(POOL[name].mesh, name)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["box_knob", "mug"])
def test_gradcheck(name):
    """torch.autograd.gradcheck in double precision with a loose edge (sigma 2 px), on the 16
    entries of the pose matrix (the bottom row's gradient is zero, as is its effect)."""
    rng = np.random.default_rng(0)
    m = mesh(name)
    cams = ring_cameras(2, rng, dist_range=(400, 450), target=(0, 0, 0), K=default_K(64, 48, 60.0), width=64, height=48)
    R = random_rotation(rng)
    T = torch.tensor(make_pose(R, -R @ m.centre), dtype=torch.float64, requires_grad=True)
    rast = SoftSilhouetteRasterizer(m)
    assert torch.autograd.gradcheck(lambda T: silhouettes(rast, T, cams, sigma=2.0), (T,), eps=1e-6, atol=1e-5,
                                    rtol=1e-3)


def twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    """4x4 ``hat(xi)`` of ``xi = (v [mm], w [0.01 rad])``."""
    w = xi[3:] * 0.01
    X = torch.zeros(4, 4, dtype=xi.dtype)
    X[0, 1], X[0, 2], X[1, 2] = -w[2], w[1], -w[0]
    X[1, 0], X[2, 0], X[2, 1] = w[2], -w[1], w[0]
    X[:3, 3] = xi[:3]
    return X


@pytest.mark.slow
@pytest.mark.parametrize("name", ["box_knob", "mug", "l_bracket"])
def test_gradient_matches_finite_differences(name):
    """The loss's gradient w.r.t. a twist (through ``matrix_exp`` and the op's matrix gradient)
    against central differences of the forward pass (steps of 1e-4 mm and 1e-6 rad), at two poses
    2 mm off the target's: within 1% of the gradient's norm. The forward pass is piecewise smooth:
    where an outline piece's visibility flips within the step (sub-pixel pieces are kept or not
    whole) a pixel's value jumps by up to a few hundredths, which no derivative describes, and a
    central difference over such a jump is meaningless. Those pixels are found the way a jump shows
    (its difference quotient doubles when the step halves), left out of the loss for both, and
    counted: at most 2% of the pixels that have a derivative."""
    rng = np.random.default_rng([1, len(name)])
    m = mesh(name)
    rast = SoftSilhouetteRasterizer(m)
    cams = ring_cameras(8, rng, dist_range=(400, 450), target=(0, 0, 0), K=default_K(160, 120, 150.0), width=160,
                        height=120)
    h = 1e-4
    for _ in range(2):
        R = random_rotation(rng)
        T0 = torch.tensor(make_pose(R, -R @ m.centre), dtype=torch.float64)
        target = silhouettes(rast, T0, cams, 1.0).detach()
        start = T0.clone()
        start[:3, 3] += torch.tensor([1.5, -1.0, 1.0], dtype=torch.float64)

        def images(xi: torch.Tensor) -> torch.Tensor:
            return silhouettes(rast, torch.linalg.matrix_exp(twist_matrix(xi)) @ start, cams, 1.0)

        quotients = {}
        with torch.no_grad():
            for k in range(6):
                for step in (h, h / 2):
                    e = torch.zeros(6, dtype=torch.float64)
                    e[k] = step
                    quotients[k, step] = (images(e) - images(-e)) / (2 * step)
        jumps = torch.zeros_like(target, dtype=torch.bool)
        moving = torch.zeros_like(jumps)
        for k in range(6):
            a, b = quotients[k, h], quotients[k, h / 2]
            jumps |= (a - b).abs() > 0.05 * b.abs() + 1e-3
            moving |= b != 0
        assert int(jumps.sum()) <= 0.02 * int(moving.sum()), (int(jumps.sum()), int(moving.sum()))
        keep = ~jumps

        def loss(xi: torch.Tensor) -> torch.Tensor:
            return silhouette_loss(images(xi) * keep, target * keep)

        xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
        loss(xi).backward()
        fd = np.zeros(6)
        with torch.no_grad():
            for k in range(6):
                e = torch.zeros(6, dtype=torch.float64)
                e[k] = h
                fd[k] = float(loss(e) - loss(-e)) / (2 * h)
        assert np.linalg.norm(xi.grad.numpy() - fd) <= 0.01 * np.linalg.norm(fd), (xi.grad, fd)


def test_batched_poses_and_kornia_se3_agree():
    """(N, 4, 4) renders each pose as one (4, 4) does; a kornia Se3 gives the same images and its
    gradient reaches the Se3's parameters."""
    rng = np.random.default_rng(2)
    meshes = [mesh("box_knob"), mesh("mug")]
    cams = ring_cameras(3, rng, dist_range=(400, 450), target=(0, 0, 0), K=default_K(96, 72, 90.0), width=96, height=72)
    Ts = [make_pose(random_rotation(rng), -m.centre) for m in meshes]
    both = silhouettes(meshes, torch.tensor(np.stack(Ts)), cams)
    assert both.shape == (2, 3, 72, 96) and both.dtype == torch.float64
    for k, (m, T) in enumerate(zip(meshes, Ts)):
        torch.testing.assert_close(both[k], silhouettes(m, torch.tensor(T), cams))
        assert 0 < float(both[k].mean()) < 1
    Se3 = kornia_liegroup.Se3
    pose = Se3.from_matrix(torch.tensor(Ts[0]))
    pose.r.q.data.requires_grad_(True)
    img = silhouettes(meshes[0], pose, cams)
    torch.testing.assert_close(img, both[0])
    img.sum().backward()
    assert pose.r.q.data.grad is not None and float(pose.r.q.data.grad.abs().sum()) > 0


def test_bad_inputs_are_clear_errors():
    m = mesh("box_knob")
    cams = ring_cameras(2, np.random.default_rng(0), K=default_K(64, 48, 60.0), width=64, height=48)
    with pytest.raises(ValueError, match="poses must be"):
        silhouettes(m, torch.zeros(3, 3), cams)
    with pytest.raises(ValueError, match="targets"):
        SilhouetteLoss(m, cams, np.zeros((3, 48, 64)))
    other = ring_cameras(1, np.random.default_rng(0), K=default_K(32, 24, 30.0), width=32, height=24)
    with pytest.raises(ValueError, match="different image sizes"):
        silhouettes(m, torch.eye(4, dtype=torch.float64), cams + other)


@pytest.mark.slow
def test_region_loss_fits_a_pose_from_photos_alone(tmp_path):
    """RegionLoss (the photos as evidence, no masks): its targets are autoalign's own region
    targets (same function, same pose), and torch.optim (Adam on a twist, the targets learned
    again every 15 steps) brings a pose 6 mm / 8 deg off to within 1 mm / 1 deg."""
    from autoalign.experiments.scenes.photo_scene import write_photo_scene
    from autoalign.experiments.scenes.synthetic import perturb_pose
    from autoalign.geometry.se3 import rotation_angle_deg
    from autoalign.io.evidence import read_evidence
    from autoalign.losses.region import RegionOptions
    from autoalign.losses.region_term import RegionTerm
    from autoalign.torch import RegionLoss

    m = mesh("box_knob")
    ps = write_photo_scene(tmp_path / "scene", [m], 8, seed=2, width=320, height=240, dist_range=(300.0, 400.0))
    scene = read_evidence(ps.folder, 0, ("photos",))
    T_true = ps.poses[0]
    T0 = perturb_pose(T_true, 6.0, 8.0, np.random.default_rng(1), m.centre)
    rast = SoftSilhouetteRasterizer(m)
    loss_fn = RegionLoss(rast, scene.cameras, scene.photos, sigma=1.0)
    loss_fn.learn(torch.tensor(T0))
    ours = RegionTerm.learned_at(scene, rast.hard_masks(T0, scene.cameras), RegionOptions())
    assert np.array_equal(loss_fn.targets.numpy(), np.stack(ours.targets).astype(np.float64))
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    base = torch.tensor(T0)
    centre = torch.tensor(T0[:3, :3] @ m.centre + T0[:3, 3])
    about = torch.eye(4, dtype=torch.float64)
    about[:3, 3] = centre
    opt = torch.optim.Adam([xi], lr=0.3)
    for step in range(90):
        T = about @ torch.linalg.matrix_exp(twist_matrix(xi)) @ torch.linalg.inv(about) @ base
        if step and step % 15 == 0:
            loss_fn.learn(T.detach())
        opt.zero_grad()
        loss_fn(T).backward()
        opt.step()
    T = (about @ torch.linalg.matrix_exp(twist_matrix(xi)) @ torch.linalg.inv(about) @ base).detach().numpy()
    c = m.centre
    err_mm = np.linalg.norm((T[:3, :3] @ c + T[:3, 3]) - (T_true[:3, :3] @ c + T_true[:3, 3]))
    print(f"region fit: {err_mm:.3f} mm {rotation_angle_deg(T[:3, :3], T_true[:3, :3]):.3f} deg")
    assert err_mm < 1.0 and rotation_angle_deg(T[:3, :3], T_true[:3, :3]) < 1.0
