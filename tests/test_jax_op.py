"""The JAX ops and solve (issue 15): ``autoalign.jax.silhouettes`` (custom_vjp) and
``pixel_silhouettes`` (custom_jvp) against ``jax.test_util.check_grads``, under ``jit`` and
``vmap``, and ``autoalign.jax.refine`` (optimistix Levenberg-Marquardt) against
``autoalign.refine`` on the same least-squares problem from the same start."""

from __future__ import annotations

import jax  # noqa: E402 - the test command installs every extra: a missing one must fail, not skip
import numpy as np
import optimistix  # noqa: E402,F401 - autoalign.jax.refine needs it
import pytest

jax.config.update("jax_enable_x64", True)  # noqa: E402 - the solve needs double precision (see autoalign.jax.refine)

import jax.numpy as jnp  # noqa: E402
from jax.test_util import check_grads  # noqa: E402

import autoalign  # noqa: E402
import autoalign.jax as aj  # noqa: E402
from autoalign.engine.objective import Level  # noqa: E402
from autoalign.experiments.scenes.procedural_models import procedural_models  # noqa: E402
from autoalign.experiments.scenes.synthetic import (  # noqa: E402
    default_K,
    perturb_pose,
    random_rotation,
    raycast_masks,
    ring_cameras,
)
from autoalign.geometry.mesh import mesh_from_trimesh  # noqa: E402
from autoalign.geometry.se3 import make_pose, rotation_angle_deg  # noqa: E402
from autoalign.io.bop import Scene  # noqa: E402

POOL = {pm.name: pm for pm in procedural_models()}


def small_op(name: str, seed: int = 0) -> tuple[aj.SilhouetteOp, jax.Array]:
    rng = np.random.default_rng(seed)
    mesh = mesh_from_trimesh(POOL[name].mesh, name)
    cams = ring_cameras(2, rng, dist_range=(400, 450), target=(0, 0, 0), K=default_K(64, 48, 60.0), width=64, height=48)
    R = random_rotation(rng)
    return aj.SilhouetteOp.of(mesh, cams, sigma=2.0), jnp.asarray(make_pose(R, -R @ mesh.centre))


@pytest.mark.parametrize("name", ["box_knob", "mug"])
def test_check_grads(name):
    """Reverse mode of the custom_vjp op and forward mode of the custom_jvp one, against JAX's own
    finite differences (double precision, a loose 2 px edge)."""
    op, T = small_op(name)
    check_grads(lambda T: aj.silhouettes(op, T), (T,), order=1, modes=["rev"], eps=1e-6, atol=1e-4, rtol=1e-3)
    every = aj.Pixels(np.arange(int(np.prod(op.shape))))
    check_grads(lambda T: aj.pixel_silhouettes(op, every, T), (T,), order=1, modes=["fwd"], eps=1e-6, atol=1e-4,
                rtol=1e-3)


def test_jit_and_vmap_agree_with_eager():
    op, T = small_op("box_knob", seed=1)
    loss = lambda T: jnp.sum(aj.silhouettes(op, T) ** 2)  # noqa: E731
    np.testing.assert_allclose(jax.jit(loss)(T), loss(T))
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(T), jax.grad(loss)(T))
    Ts = jnp.stack([T, T.at[0, 3].add(2.0), T.at[1, 3].add(-1.0)])
    batched = jax.vmap(lambda T: aj.silhouettes(op, T))(Ts)
    for k in range(3):
        np.testing.assert_allclose(batched[k], aj.silhouettes(op, Ts[k]))
    assert not np.allclose(batched[0], batched[1])


@pytest.mark.slow
def test_optimistix_solve_matches_autoalign_refine():
    """The same multi-view least squares (l2 loss, no robust weights) from a start 5 mm / 5 deg off:
    optimistix's LM lands within 0.01 mm and 0.01 deg of autoalign.refine solved to convergence
    (within 0.0002 mm / 0.0005 deg on three scenes). autoalign.refine's default full-resolution
    level stops once a step would gain less than 0.1% of the loss, 0.01-0.02 mm / 0.035 deg before
    that minimum here, which is why the comparison tightens its tolerance."""
    rng = np.random.default_rng(3)
    mesh = mesh_from_trimesh(POOL["box_knob"].mesh)
    cams = ring_cameras(20, rng, target=(0, 0, 0), K=default_K(320, 240, 300.0), width=320, height=240)
    R = random_rotation(rng)
    T_true = make_pose(R, -R @ mesh.centre)
    scene = Scene(list(cams), [m.astype(np.float32) for m in raycast_masks(mesh, T_true, cams)], list(range(20)))
    T0 = perturb_pose(T_true, 5.0, 5.0, rng, mesh.centre)
    converged = (Level(0.25, 1.0, 40), Level(1.0, 0.5, 60, ftol=1e-9))
    native = autoalign.refine(scene, mesh, seed=T0, options=autoalign.RefineOptions(robust=False, schedule=converged)).T_wm
    ours = aj.refine(scene, mesh, T0)
    centre = lambda T: T[:3, :3] @ mesh.centre + T[:3, 3]  # noqa: E731
    assert np.linalg.norm(centre(ours.T_wm) - centre(native)) < 0.01
    assert rotation_angle_deg(ours.T_wm[:3, :3], native[:3, :3]) < 0.01
    assert np.linalg.norm(centre(ours.T_wm) - centre(T_true)) < 0.05


def test_refine_needs_double_precision():
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(ValueError, match="jax_enable_x64"):
            aj.refine(Scene([], [], []), mesh_from_trimesh(POOL["box_knob"].mesh), np.eye(4))
    finally:
        jax.config.update("jax_enable_x64", True)
