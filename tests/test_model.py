"""Exact properties of GA3CE's pieces: rotations, egocentric transform, encodings, model, loss."""
import numpy as np
import pytest
import torch

from ga3ce_prep.model import (
    GA3CE,
    ModelConfig,
    angular_loss,
    axis_angle_rotation,
    cyclotorsion_rotation,
    d3_encoding,
    egocentric_transform,
    fourier_features,
    gaze_cone_bias,
    pose_normalization,
)
from ga3ce_prep.skeleton import GA3CE_JOINTS

torch.set_num_threads(2)
ROTATIONS = [cyclotorsion_rotation, axis_angle_rotation]


def _directions(n=2000, seed=0):
    """Random unit vectors plus the hard cases: exactly and nearly +-y, -z and +z."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    e = 1e-7
    hard = [[0, 1, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1], [-0.0, 0, -1], [e, 1, 0], [e, -1, -e],
            [e, e, -1], [-e, 0, -1], [0, e, -1], [e, 0, 1], [1e-4, 1, 1e-4], [1e-4, -1e-4, -1]]
    v = np.concatenate([v, hard])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("fn", ROTATIONS)
def test_rotation_maps_v_to_z(fn):
    v = _directions()
    R = fn(v)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, v), np.tile([0, 0, 1.0], (len(v), 1)), atol=1e-6)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-6)
    # float32 torch as the trainer runs it
    v32 = torch.tensor(v, dtype=torch.float32)
    z = torch.einsum("nij,nj->ni", fn(v32), v32)
    assert (z - torch.tensor([0, 0, 1.0])).abs().max() < 1e-6


@pytest.mark.parametrize("fn", ROTATIONS)
def test_torch_and_numpy_agree(fn):
    v = _directions(500, seed=1) * np.random.default_rng(2).uniform(0.5, 3, (513, 1))  # any length
    np.testing.assert_allclose(fn(torch.tensor(v)).numpy(), fn(v), atol=1e-12)
    np.testing.assert_allclose(fn(torch.tensor(v, dtype=torch.float32)).numpy(), fn(v), atol=2e-6)


def test_cyclotorsion_has_no_roll_axis_angle_rolls():
    v = _directions()
    assert np.all(cyclotorsion_rotation(v)[:, 0, 1] == 0)
    assert torch.all(cyclotorsion_rotation(torch.tensor(v, dtype=torch.float32))[:, 0, 1] == 0)
    generic = v[:2000]
    generic = generic[(np.abs(generic[:, 0]) > 0.1) & (np.abs(generic[:, 1]) > 0.1)]
    roll = np.abs(axis_angle_rotation(generic)[:, 0, 1])
    assert roll.min() > 1e-4
    assert np.median(roll) > 0.05
    # the paper's closed form for one v: phi = atan2(-vx, vz), theta = atan2(vy, vz cos phi - vx sin phi)
    vx, vy, vz = 0.3, -0.4, np.sqrt(1 - 0.25)
    phi = np.arctan2(-vx, vz)
    theta = np.arctan2(vy, vz * np.cos(phi) - vx * np.sin(phi))
    Rx = np.array([[1, 0, 0], [0, np.cos(theta), -np.sin(theta)], [0, np.sin(theta), np.cos(theta)]])
    Ry = np.array([[np.cos(phi), 0, np.sin(phi)], [0, 1, 0], [-np.sin(phi), 0, np.cos(phi)]])
    np.testing.assert_allclose(cyclotorsion_rotation(np.array([vx, vy, vz])), Rx @ Ry, atol=1e-12)


def _scene(B=6, S=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    head = torch.tensor([0.3, -0.2, 3.0]) + 0.5 * torch.randn(B, 3, generator=g)
    pose = head[:, None] + 0.4 * torch.randn(B, 30, 3, generator=g)
    view = torch.nn.functional.normalize(torch.randn(B, 3, generator=g), dim=-1)
    objects = head[:, None] + 2 * torch.randn(B, S, 3, generator=g)
    mask = torch.rand(B, S, generator=g) < 0.8
    mask[:, 0] = True
    return view, pose.double(), head, objects, mask


def test_pose_normalisation_and_scale_invariance():
    view, pose, head, objects, mask = _scene()
    t, s, ok = pose_normalization(pose)
    np.testing.assert_allclose(t, pose[:, 24:30].mean(1), atol=1e-12)
    np.testing.assert_allclose(s, 1 / torch.linalg.vector_norm(pose[:, 24] - pose[:, 28], dim=-1), atol=1e-9)
    a = egocentric_transform(view.double(), pose, objects.double(), head.double())
    for k, shift in [(2.5, 0.0), (0.3, 1.7)]:  # scaling the pose changes t_pose and the head width together
        b = egocentric_transform(view.double(), k * pose + shift, objects.double(), head.double())
        np.testing.assert_allclose(b.pose, a.pose, atol=1e-9)
    assert a.pose.shape == (6, len(GA3CE_JOINTS), 3)
    assert a.joint_valid.all()
    np.testing.assert_allclose(a.view, torch.tensor([[0, 0, 1.0]]).expand(6, 3), atol=1e-12)
    # objects keep their distance from the head and their angle to v
    rel = objects.double() - head.double()[:, None]
    np.testing.assert_allclose(torch.linalg.vector_norm(a.objects, dim=-1), torch.linalg.vector_norm(rel, dim=-1),
                               atol=1e-9)
    cos = torch.nn.functional.normalize(rel, dim=-1) @ view.double()[0]
    np.testing.assert_allclose(torch.nn.functional.normalize(a.objects[0], dim=-1)[:, 2], cos[0], atol=1e-9)


def test_missing_pose_policy():
    view, pose, head, objects, mask = _scene(B=3)
    pose = pose.clone()
    pose[0] = float("nan")            # whole pose missing
    pose[1, 28] = float("nan")        # head-width joint missing -> whole pose unusable
    pose[2, 7] = float("nan")         # one ankle missing -> only that joint
    ctx = egocentric_transform(view.double(), pose, objects.double(), head.double())
    assert not ctx.joint_valid[0].any()
    assert not ctx.joint_valid[1].any()
    assert ctx.joint_valid[2].sum() == 14
    assert not ctx.joint_valid[2, GA3CE_JOINTS.index(7)]
    assert torch.isfinite(ctx.pose).all()


def test_encoding_widths():
    m = GA3CE(ModelConfig())
    p = torch.randn(4, 5, 3)
    assert m.view_encoding(p[:, 0]).shape == (4, 106)
    assert m.pose_encoding(torch.randn(4, 15, 3)).shape == (4, 15, 10)
    assert m.object_encoding(p).shape == (4, 5, 256)
    assert m.subject_embedding(torch.randn(4, 3), torch.randn(4, 15, 3),
                               torch.ones(4, 15, dtype=torch.bool)).shape == (4, 256)
    s = GA3CE(ModelConfig(encoding="standard"))
    assert s.pose_encoding(torch.randn(4, 15, 3)).shape == (4, 15, 10)
    assert s.object_encoding(p).shape == (4, 5, 256)
    # D3 = gamma(direction) ++ gamma(distance): scaling a point changes only the distance half
    B_dir, B_dist = m.object_encoding.B_dir, m.object_encoding.B_dist
    e1, e2 = d3_encoding(p, B_dir, B_dist), d3_encoding(3 * p, B_dir, B_dist)
    torch.testing.assert_close(e1[..., :128], e2[..., :128])
    assert (e1[..., 128:] - e2[..., 128:]).abs().max() > 0.1
    x = torch.tensor([[0.25, 0.0, 0.0]])
    torch.testing.assert_close(fourier_features(x, torch.tensor([[1.0, 0, 0]])), torch.tensor([[0.0, 1.0]]),
                               atol=1e-6, rtol=0)


@pytest.mark.parametrize("cfg", [ModelConfig(), ModelConfig(rotation="axis_angle", encoding="standard"),
                                 ModelConfig(rotation="none", use_pose=False), ModelConfig.for_method("ours")])
def test_padding_does_not_change_prediction(cfg):
    torch.manual_seed(0)
    m = GA3CE(cfg).eval()
    view, pose, head, objects, mask = _scene(B=5, S=7)
    pose = pose.float()
    with torch.no_grad():
        g = m(view, pose, head, objects, mask)
        junk = 50 * torch.randn(5, 30, 3)
        obj2 = torch.cat([torch.where(mask[..., None], objects, junk[:, :7]), junk[:, 7:20]], 1)
        mask2 = torch.cat([mask, torch.zeros(5, 13, dtype=torch.bool)], 1)
        g2 = m(view, pose, head, obj2, mask2)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(g2, g, atol=1e-5, rtol=0)
    torch.testing.assert_close(g.norm(dim=-1), torch.ones(5), atol=1e-6, rtol=0)


@pytest.mark.parametrize("output", ["pointer", "regress"])
def test_zero_objects_and_missing_pose_are_valid_samples(output):
    torch.manual_seed(0)
    m = GA3CE(ModelConfig(output=output)).eval()
    view, pose, head, objects, mask = _scene(B=4, S=6)
    pose = pose.float()
    pose[1] = float("nan")
    mask[2] = False
    with torch.no_grad():
        g = m(view, pose, head, objects, mask)
        g0 = m(view, pose, head, objects[:, :0], mask[:, :0])   # nobody has objects
        no_obj = GA3CE(ModelConfig(use_objects=False)).eval()
        no_obj.load_state_dict(m.state_dict(), strict=False)      # the pointer's weights stay out
        a = no_obj(view, pose, head, objects, mask)
        b = no_obj(view, pose, head, torch.randn_like(objects), torch.ones_like(mask))
    assert torch.isfinite(g).all()
    assert torch.isfinite(g0).all()
    torch.testing.assert_close(g[2], g0[2], atol=1e-5, rtol=0)  # a frame with no objects == no objects at all
    torch.testing.assert_close(a, b)                               # the no-objects ablation ignores objects
    torch.testing.assert_close(a, g0, atol=1e-5, rtol=0)


def test_residual_output_and_appearance_only():
    view, pose, head, objects, mask = _scene(B=4)
    m = GA3CE(ModelConfig(output="regress")).eval()
    for p in m.head.net[-1].parameters():  # g' = 0 -> g = v
        torch.nn.init.zeros_(p)
    with torch.no_grad():
        torch.testing.assert_close(m(view, pose.float(), head, objects, mask), view)
        # g' along z in the egocentric frame turns into v itself, any length
        m.head.net[-1].bias.copy_(torch.tensor([0, 0, 2.0]))
        torch.testing.assert_close(m(view, pose.float(), head, objects, mask), view, atol=1e-6, rtol=0)
        # g' along x in the egocentric frame is R^T x: 45 degrees off v for |g'| = 1
        m.head.net[-1].bias.copy_(torch.tensor([1.0, 0, 0]))
        g = m(view, pose.float(), head, objects, mask)
    np.testing.assert_allclose(np.degrees(np.arccos((g * view).sum(-1).numpy())), 45.0, atol=1e-4)
    ctx = GA3CE(ModelConfig(use_context=False))
    assert len(list(ctx.parameters())) == 0
    torch.testing.assert_close(ctx(3 * view, pose.float(), head, objects, mask), view)


def test_gaze_cone_bias():
    view = torch.tensor([[0, 0, 1.0]])
    objects = torch.tensor([[[0, 0, 2.0], [1, 0, 0], [0, 0, -1], [5, 5, 5]]])
    mask = torch.tensor([[True, True, True, False]])
    b = gaze_cone_bias(view, objects, mask, n_heads=2)
    assert b.shape == (2, 1, 5)
    torch.testing.assert_close(b[0, 0, :4], torch.tensor([0.0, 1.0, 0.0, -1.0]))
    assert b[1, 0, 4] == float("-inf")


def test_loss_gradient_finite_at_both_poles():
    gt = torch.nn.functional.normalize(torch.randn(8, 3, dtype=torch.float64), dim=-1)
    for sign in (1.0, -1.0):
        g = (sign * gt).clone().requires_grad_(True)
        loss = angular_loss(g, gt)
        loss.backward()
        assert torch.isfinite(loss)
        assert torch.isfinite(g.grad).all()
        # through the model's residual normalisation too: g = normalise(g' + v)
        gp = torch.zeros(8, 3, dtype=torch.float64, requires_grad=True)
        out = torch.nn.functional.normalize(gp + sign * gt, dim=-1, eps=1e-9)
        angular_loss(out, gt).backward()
        assert torch.isfinite(gp.grad).all()
    np.testing.assert_allclose(angular_loss(-gt, gt).item(), np.pi, atol=2e-3)
    a = torch.tensor([[1.0, 0, 0]])
    b = torch.tensor([[np.cos(0.3), np.sin(0.3), 0]], dtype=torch.float32)
    np.testing.assert_allclose(angular_loss(a, b).item(), 0.3, atol=1e-6)


def test_model_gradient_finite_through_whole_model():
    torch.manual_seed(0)
    m = GA3CE().train()
    view, pose, head, objects, mask = _scene(B=4)
    g = m(view, pose.float(), head, objects, mask)
    for target in (g.detach(), -g.detach()):
        m.zero_grad()
        angular_loss(m(view, pose.float(), head, objects, mask), target).backward()
        assert all(torch.isfinite(p.grad).all() for p in m.parameters() if p.grad is not None)


SMALL = dict(num_encoder_layers=1, num_decoder_layers=2, dim_feedforward=128, head_hidden=128)


@pytest.mark.parametrize("cfg", [ModelConfig(output="regress", **SMALL),
                                 ModelConfig(output="regress", cone_bias=False, rotation="none", **SMALL),
                                 ModelConfig(use_objects=False, **SMALL), ModelConfig(output="pointer", **SMALL)])
@pytest.mark.parametrize("grad", [False, True])
def test_attention_hook_leaves_outputs_identical(cfg, grad):
    torch.manual_seed(0)
    m = GA3CE(cfg).eval()
    view, pose, head, objects, mask = _scene(B=5, S=8)
    mask[2] = False                                                      # a frame without objects
    x = (view, pose.float(), head, objects, mask)
    with torch.set_grad_enabled(grad):
        g = m(*x)
        g_hooked, w = m.cross_attention(*x)
        g_after = m(*x)
    assert torch.equal(g, g_hooked) and torch.equal(g, g_after)       # bit-identical, and the hooks are gone
    S = 8 if cfg.use_objects and cfg.output == "regress" else 0   # the pointer's decoder sees the null token alone
    assert w.shape == (5, cfg.num_decoder_layers, cfg.n_heads, 1 + S)
    # sums to 1 over [null, objects]
    torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[:-1]), atol=1e-6, rtol=0)
    assert (w >= 0).all()
    if S:
        assert (w[..., 1:].permute(0, 3, 1, 2)[~mask] == 0).all()                          # padding gets nothing
        torch.testing.assert_close(w[2, ..., 0], torch.ones(w.shape[1:3]))                  # no objects: the null token
    else:
        assert (w == 1).all()


def test_pointer_first_pass_is_the_network_without_objects():
    torch.manual_seed(0)
    two = GA3CE(ModelConfig.for_method("ours", **SMALL)).eval()   # ours: output pointer
    one = GA3CE(ModelConfig(output="regress", **SMALL)).eval()
    missing, unexpected = one.load_state_dict(two.state_dict(), strict=False)   # same weights, no pointer
    assert not missing and all(k.startswith("pointer.") for k in unexpected)
    view, pose, head, objects, mask = _scene(B=5, S=8)
    x = (view, pose.float(), head, objects, mask)
    with torch.no_grad():
        g0, g = two(*x, all_passes=True)
        torch.testing.assert_close(g0, one(view, pose.float(), head, objects[:, :0], mask[:, :0]))   # g0: no objects
        assert torch.equal(g, two(*x))                        # forward's g is the last pass
        g_w, p = two.object_weights(*x)
    assert torch.equal(g_w, g) and p.shape == (5, 9)
    torch.testing.assert_close(p.sum(-1), torch.ones(5))
    assert (p[:, 1:][~mask] == 0).all()                      # padding gets nothing
    # checkpoints written before the pointer existed hold the paper's model; those written before
    # methods had names are named by their output (the pointer of then: g0 trained jointly)
    old = {k: v for k, v in ModelConfig().to_dict().items()
           if k not in ("method", "output", "pointer_kappa", "pointer_g0")}
    assert ModelConfig.from_dict(old).output == "regress" and ModelConfig.from_dict(old).method == "ga3ce"
    assert ModelConfig.from_dict({**old, "output": "pointer"}).method == "pointer-joint"
    with pytest.raises(ValueError, match="output"):
        ModelConfig(output="select")


def test_pointer_output_points_at_the_axis_or_an_object():
    torch.manual_seed(0)
    m = GA3CE(ModelConfig(output="pointer", pointer_kappa=20.0, **SMALL)).eval()
    for lin in (m.pointer.q, m.pointer.k):                   # no learned preference: the bias alone weighs
        torch.nn.init.zeros_(lin.weight), torch.nn.init.zeros_(lin.bias)
    view, pose, head, objects, mask = _scene(B=5, S=8)
    mask[3] = False                                          # a frame without objects
    with torch.no_grad():
        g0, g = m(view, pose.float(), head, objects, mask, all_passes=True)
    # p over [null, objects] ~ exp([0, 20 (cos(g0, u_i) - 1)]), g = normalise(p_null g0 + sum p_i u_i)
    u = np.asarray(torch.nn.functional.normalize(objects - head[:, None], dim=-1), np.float64)
    g0n = np.asarray(g0, np.float64)
    logits = np.where(mask.numpy(), 20.0 * (np.einsum("bsk,bk->bs", u, g0n) - 1.0), -np.inf)
    p = np.exp(np.concatenate([np.zeros((5, 1)), logits], 1))
    p /= p.sum(1, keepdims=True)
    expect = p[:, :1] * g0n + np.einsum("bs,bsk->bk", p[:, 1:], u)
    np.testing.assert_allclose(g.numpy(), expect / np.linalg.norm(expect, axis=1, keepdims=True), atol=1e-5)
    torch.testing.assert_close(g[3], g0[3])                  # no objects: the first pass's g0
    # the no-objects ablation of a pointer model regresses like the paper's (nothing to point at)
    m0 = GA3CE(ModelConfig(output="pointer", use_objects=False, **SMALL)).eval()
    paper = GA3CE(ModelConfig(output="regress", use_objects=False, **SMALL)).eval()
    assert not hasattr(m0, "pointer")
    paper.load_state_dict(m0.state_dict())
    with torch.no_grad():
        assert torch.equal(m0(view, pose.float(), head, objects, mask), paper(view, pose.float(), head, objects, mask))
    with pytest.raises(ValueError, match="output"):
        ModelConfig(output="select")


def test_attention_hook_refuses_training_mode_and_appearance_only():
    view, pose, head, objects, mask = _scene()
    x = (view, pose.float(), head, objects, mask)
    with pytest.raises(RuntimeError, match="eval mode"):
        GA3CE(ModelConfig(**SMALL)).train().cross_attention(*x)
    with pytest.raises(RuntimeError, match="eval mode"):
        GA3CE(ModelConfig(output="pointer", **SMALL)).train().cross_attention(*x)
    with pytest.raises(ValueError, match="no attention"):
        GA3CE(ModelConfig(use_context=False)).eval().cross_attention(*x)
