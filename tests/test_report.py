"""The decoder's attention hook, the paper's figures, and `ga3ce-prep report` (rendered in headless
chromium)."""
import pytest
import torch

from ga3ce_prep.model import GA3CE, ModelConfig

torch.set_num_threads(2)
SMALL = dict(num_encoder_layers=1, num_decoder_layers=2, dim_feedforward=128, head_hidden=128)


def _inputs(B=5, S=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    head = torch.tensor([0.3, -0.2, 3.0]) + 0.5 * torch.randn(B, 3, generator=g)
    pose = head[:, None] + 0.3 * torch.randn(B, 30, 3, generator=g)
    view = torch.nn.functional.normalize(torch.randn(B, 3, generator=g), dim=-1)
    objects = head[:, None] + 2 * torch.randn(B, S, 3, generator=g)
    mask = torch.arange(S)[None] < torch.tensor([S, 3, 0, 5, 1])[:B, None]    # frame 2: no objects
    return view, pose, head, objects * mask[..., None], mask


@pytest.mark.parametrize("cfg", [ModelConfig(**SMALL), ModelConfig(cone_bias=False, rotation="none", **SMALL),
                                 ModelConfig(use_objects=False, **SMALL)])
@pytest.mark.parametrize("grad", [False, True])
def test_attention_hook_leaves_outputs_identical(cfg, grad):
    torch.manual_seed(0)
    m = GA3CE(cfg).eval()
    x = _inputs()
    with torch.set_grad_enabled(grad):
        g = m(*x)
        g_hooked, w = m.cross_attention(*x)
        g_after = m(*x)
    assert torch.equal(g, g_hooked) and torch.equal(g, g_after)       # bit-identical, and the hooks are gone
    S = 0 if not cfg.use_objects else x[3].shape[1]
    assert w.shape == (5, cfg.num_decoder_layers, cfg.n_heads, 1 + S)
    torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[:-1]), atol=1e-6, rtol=0)   # sums to 1 over [null, objects]
    assert (w >= 0).all()
    if S:
        mask = x[4]
        assert (w[..., 1:][~mask[:, None, None].expand(-1, *w.shape[1:3], -1)] == 0).all()   # padding gets nothing
        torch.testing.assert_close(w[2, ..., 0], torch.ones(w.shape[1:3]))                  # no objects: the null token
    else:
        assert (w == 1).all()


def test_attention_hook_refuses_training_mode_and_appearance_only():
    m = GA3CE(ModelConfig(**SMALL)).train()
    with pytest.raises(RuntimeError, match="eval mode"):
        m.cross_attention(*_inputs())
    with pytest.raises(ValueError, match="no attention"):
        GA3CE(ModelConfig(use_context=False)).eval().cross_attention(*_inputs())
