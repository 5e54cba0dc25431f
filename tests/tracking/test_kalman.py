"""Each light's filter: still lights averaged, moving ones followed, lights paired to tracks."""

import torch

from selfsup.tracking.kalman import pair_lights, predict, start_state, update


def test_a_still_light_s_noisy_measurements_are_averaged():
    gen = torch.Generator().manual_seed(0)
    truth = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    sigma = 0.01
    cov = torch.eye(3, dtype=torch.float64) * sigma**2
    state = start_state(truth + sigma * torch.randn(3, generator=gen, dtype=torch.float64), cov, 0.01)
    for _ in range(40):
        state = update(predict(state, 1e-5), truth + sigma * torch.randn(3, generator=gen, dtype=torch.float64), cov)
    assert float((state.position - truth).norm()) < 0.4 * sigma * 3**0.5  # well below one measurement's error
    assert float(state.position_cov.diagonal().max()) < 0.2 * sigma**2


def test_a_light_moving_steadily_is_followed_without_lag():
    step = torch.tensor([0.02, 0.0, -0.01], dtype=torch.float64)
    cov = torch.eye(3, dtype=torch.float64) * 1e-6
    state = start_state(torch.zeros(3, dtype=torch.float64), cov, 0.05)
    for t in range(1, 30):
        state = update(predict(state, 1e-3), t * step, cov)
    assert float((state.position - 29 * step).norm()) < 1e-3
    assert torch.allclose(state.mean[3:], step, atol=1e-3)


def test_the_covariance_stays_symmetric_and_positive():
    cov = torch.tensor([[4e-4, 1e-4, 0], [1e-4, 2e-4, 0], [0, 0, 1e-4]], dtype=torch.float64)
    state = start_state(torch.zeros(3, dtype=torch.float64), cov, 0.1)
    for _ in range(20):
        state = update(predict(state, 0.01), torch.zeros(3, dtype=torch.float64), cov)
    assert torch.equal(state.cov, state.cov.T)
    assert float(torch.linalg.eigvalsh(state.cov).min()) > 0


def test_lights_pair_with_the_nearest_tracks_and_far_ones_start_new():
    tracked = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    found = torch.tensor([[1.02, 0, 0], [5.0, 0, 0], [0.01, 0, 0]])
    assert pair_lights(tracked, found, radius=0.1) == [1, None, 0]
    assert pair_lights(torch.zeros(0, 3), found, 0.1) == [None, None, None]
    assert pair_lights(tracked, torch.zeros(0, 3), 0.1) == []
