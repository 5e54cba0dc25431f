import pytest
import torch

from render import GBuffer, Material, PointLights, ShadowedBlinnPhong


def _inputs(device, dtype=torch.float32):
    K = torch.tensor([[20.0, 0, 7.5], [0, 20.0, 7.5], [0, 0, 1]], device=device)
    depth = torch.full((2, 16, 16), 2.0, device=device)
    depth[:, 4:8, 4:8] = 1.5
    g = GBuffer.from_depth(depth, K)
    mat = Material(kd=torch.full((2, 16, 16, 3), 0.5, device=device), ks=torch.full((2, 16, 16, 1), 0.2, device=device), shininess=30.0)
    lights = PointLights(position=torch.tensor([[[0.2, -0.5, 1.0]]] * 2, device=device, requires_grad=True),
                         intensity=torch.ones(2, 1, 3, device=device))
    return g, mat, lights


@pytest.mark.parametrize("device", [
    pytest.param("cpu", marks=pytest.mark.slow),
    pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]),
])
@pytest.mark.parametrize("method", ["epipolar", "paper"])
def test_torch_compile_matches_eager(method, device):
    g, mat, lights = _inputs(device)
    layer = ShadowedBlinnPhong(shadows=method, check_finite=False)
    compiled = torch.compile(layer)
    out = compiled(g, mat, lights)
    out.sum().backward()
    torch.testing.assert_close(out, layer(g, mat, lights), atol=1e-5, rtol=1e-5)
    assert torch.isfinite(lights.position.grad).all()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("method", ["epipolar", "paper", "none"])
def test_cuda_autocast_bf16(method):
    g, mat, lights = _inputs("cuda")
    layer = ShadowedBlinnPhong(shadows=method)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        out = layer(g, mat, lights)
    out.float().sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(lights.position.grad).all()
    ref = layer(g, mat, PointLights(position=lights.position.detach(), intensity=lights.intensity))
    assert (out.float() - ref).abs().max() < 0.05 * ref.abs().max()
