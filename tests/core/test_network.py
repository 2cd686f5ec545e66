"""core.network: the forward-Laplacian derivatives against nested autograd, both kernel paths,
and the geometric initialisation.

The compiled kernels are shared by every test of the process (``network._kernels``), so only the
first compiled test of each kind pays for torch.compile. Torch runs on one thread: the networks
are small, and two OpenMP threads on a shared two-core machine can run 10-50x slower.
"""

from __future__ import annotations

import logging

import pytest
import torch

from core import network
from core.network import ImplicitNetwork, derivatives_autograd

# (depth, width, beta): depth 1 has no hidden-to-hidden layer, so it runs first_activation only.
ARCHITECTURES = [(1, 32, 1.0), (1, 24, 100.0), (2, 16, 100.0), (2, 40, 1.0), (4, 24, 100.0), (4, 16, 1.0)]
# (depth, width, beta, Fourier features): the first layer reads the encoding as a hidden layer does.
ENCODED = [(1, 16, 100.0, 3), (2, 24, 200.0, 8), (4, 16, 1.0, 5)]
N_ROWS = 50
SUBSET = 17
LAPLACIAN_ROWS = {"all": None, "subset": SUBSET, "none": 0}


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(params=["eager", "compiled"])
def kernels(request, monkeypatch):
    """Run the test with the eager kernels, then with the torch.compile'd ones (no fallback)."""
    shared = network._kernels
    monkeypatch.setattr(shared, "compiled", request.param == "compiled")
    yield request.param
    if request.param == "compiled":
        assert not shared.fell_back, "torch.compile failed and the kernels fell back to eager (see the log)"
        assert shared._functions, "the compiled kernels were not used"


def random_network(depth, width, beta, seed=0, dtype=torch.float64, features=0) -> ImplicitNetwork:
    """A geometrically initialised network whose weights and biases are then perturbed at random
    (the Fourier features' weights too, which start at zero)."""
    generator = torch.Generator().manual_seed(seed)
    model = ImplicitNetwork(width, depth, beta, generator=generator, features=features, frequency=2.0).to(dtype)
    with torch.no_grad():
        for parameter in model.parameters():
            scale = parameter.square().mean().sqrt().item() or 0.1
            parameter.add_(0.5 * scale * torch.randn(parameter.shape, generator=generator, dtype=dtype))
    return model


def random_points(n=N_ROWS, seed=1, dtype=torch.float64) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=generator, dtype=dtype) * 2 - 1


def as_double(model: ImplicitNetwork) -> ImplicitNetwork:
    features = len(model.frequencies)
    copy = ImplicitNetwork(model.layers[0].out_features, len(model.layers) - 1, model.beta, features=features).double()
    copy.load_state_dict({name: value.double() for name, value in model.state_dict().items()})
    return copy


def loss_of(f, grad, lap):
    loss = f.abs().mean() + (grad.norm(dim=1) - 1).square().mean()
    return loss if lap is None else loss + lap.square().mean()


def relative(actual: torch.Tensor, expected: torch.Tensor) -> float:
    """Largest absolute difference over the largest reference magnitude."""
    scale = expected.abs().max().item()
    assert scale > 0, "the reference is identically zero: the comparison would prove nothing"
    return (actual.double() - expected.double()).abs().max().item() / scale


def check_against_reference(model, x, rows, tol_values, tol_weights):
    """f, ∇f, Δf and the weight gradients of a loss on them, fast path vs nested autograd (float64)."""
    f, grad, lap = model.derivatives(x, laplacian_rows=rows)
    reference_model = as_double(model)
    f_ref, grad_ref, lap_ref = derivatives_autograd(reference_model, x.double())
    m = len(x) if rows is None else rows
    lap_ref = lap_ref[:m] if m else None

    assert f.shape == (len(x),) and grad.shape == (len(x), 3) and f.dtype == x.dtype
    assert relative(f, f_ref) <= tol_values
    assert relative(grad, grad_ref) <= tol_values
    if m:
        assert lap.shape == (m,)
        assert relative(lap, lap_ref) <= tol_values
    else:
        assert lap is None

    weights = list(model.parameters())
    fast = torch.autograd.grad(loss_of(f, grad, lap), weights)
    slow = torch.autograd.grad(loss_of(f_ref, grad_ref, lap_ref), list(reference_model.parameters()))
    for (name, _), g_fast, g_slow in zip(model.named_parameters(), fast, slow):
        assert relative(g_fast, g_slow) <= tol_weights, name


@pytest.mark.parametrize("rows", LAPLACIAN_ROWS.values(), ids=LAPLACIAN_ROWS.keys())
@pytest.mark.parametrize("depth, width, beta", ARCHITECTURES)
def test_derivatives_match_autograd_float64(kernels, depth, width, beta, rows):
    model = random_network(depth, width, beta)
    check_against_reference(model, random_points(), rows, tol_values=1e-8, tol_weights=1e-8)


@pytest.mark.parametrize("rows", LAPLACIAN_ROWS.values(), ids=LAPLACIAN_ROWS.keys())
@pytest.mark.parametrize("depth, width, beta, features", ENCODED)
def test_derivatives_through_fourier_features_match_autograd_float64(kernels, depth, width, beta, features, rows):
    model = random_network(depth, width, beta, features=features)
    check_against_reference(model, random_points(), rows, tol_values=1e-8, tol_weights=1e-8)


@pytest.mark.parametrize("depth, width, beta, features", ENCODED)
def test_reverse_mode_gradient_through_fourier_features_matches_autograd_float64(depth, width, beta, features):
    model = random_network(depth, width, beta, features=features)
    x = random_points()
    f, grad = model.gradient(x)
    f_ref, grad_ref, _ = derivatives_autograd(as_double(model), x)
    assert relative(f, f_ref) <= 1e-12
    assert relative(grad, grad_ref) <= 1e-12
    torch.testing.assert_close(model(x), f_ref, rtol=0, atol=1e-12)


def test_fourier_features_start_with_no_weight_so_the_initial_sphere_is_the_same():
    """Whatever the frequencies, the initial f is the geometric initialisation's."""
    low, high = (
        ImplicitNetwork(32, 2, 100.0, generator=torch.Generator().manual_seed(4), features=8, frequency=q)
        for q in (1.0, 8.0)
    )
    x, _, _ = shell_points(200)
    with torch.no_grad():
        assert not torch.equal(low.frequencies, high.frequencies)
        torch.testing.assert_close(low(x), high(x), rtol=0, atol=0)
        assert low.encode(x).shape == (200, 3 + 16)
    # Each feature is divided by its |b|, so that none rises faster than x (slope at most 1).
    features = low.encode(x)[:, 3:]
    assert features.abs().max() <= (1 / low.frequencies.norm(dim=1)).max() + 1e-6


@pytest.mark.parametrize("rows", LAPLACIAN_ROWS.values(), ids=LAPLACIAN_ROWS.keys())
@pytest.mark.parametrize("depth, width, beta", [(1, 32, 100.0), (4, 24, 100.0), (2, 40, 1.0)])
def test_derivatives_float32_close_to_float64_reference(kernels, depth, width, beta, rows):
    model = random_network(depth, width, beta, dtype=torch.float32)
    x = random_points(dtype=torch.float32)
    check_against_reference(model, x, rows, tol_values=2e-5, tol_weights=1e-3)


@pytest.mark.parametrize("depth, width, beta", ARCHITECTURES + [(4, 32, 200.0)])
def test_reverse_mode_gradient_matches_autograd_float64(depth, width, beta):
    model = random_network(depth, width, beta)
    x = random_points()
    f, grad = model.gradient(x)
    f_ref, grad_ref, _ = derivatives_autograd(as_double(model), x)
    assert f.shape == (len(x),) and grad.shape == (len(x), 3)
    assert relative(f, f_ref) <= 1e-12
    assert relative(grad, grad_ref) <= 1e-12


@pytest.mark.parametrize("depth, width, beta", [(1, 32, 100.0), (4, 24, 100.0), (4, 64, 200.0)])
def test_reverse_mode_gradient_float32_as_close_as_the_forward_mode(depth, width, beta):
    """The extraction's float32 ∇f: within float32 rounding of the float64 reference, as the
    forward-mode ∇f is."""
    model = random_network(depth, width, beta, dtype=torch.float32)
    x = random_points(200, dtype=torch.float32)
    f_ref, grad_ref, _ = derivatives_autograd(as_double(model), x.double())
    with torch.no_grad():
        f, grad = model.gradient(x)
        _, grad_forward, _ = model.derivatives(x, laplacian_rows=0)
    assert relative(f, f_ref) <= 2e-6
    assert relative(grad, grad_ref) <= max(2e-6, 2 * relative(grad_forward, grad_ref))


def test_laplacian_is_not_trivial():
    """The comparisons above are meaningful: the perturbed networks have large, varied Δf."""
    model = random_network(4, 24, 100.0)
    _, grad, lap = model.derivatives(random_points())
    assert lap.abs().max() > 1.0 and lap.std() > 0.1
    assert (grad.norm(dim=1) > 0.01).all()


def test_derivatives_value_equals_forward(kernels):
    model = random_network(2, 16, 100.0, dtype=torch.float32)
    x = random_points(dtype=torch.float32)
    f, _, _ = model.derivatives(x)
    torch.testing.assert_close(f, model(x), rtol=1e-5, atol=1e-6)


def _compile_failing_with(error: Exception):
    """A stand-in for torch.compile whose compiled functions raise ``error`` when called."""

    def broken_compile(function, **kwargs):
        def fail(*args):
            raise error

        return fail

    return broken_compile


def test_a_kernel_whose_compilation_fails_runs_eagerly_and_the_failure_is_logged_once(monkeypatch, caplog):
    from torch._dynamo.exc import BackendCompilerFailed

    failure = BackendCompilerFailed(torch.compile, RuntimeError("no C++ compiler (simulated)"), None)
    monkeypatch.setattr(torch, "compile", _compile_failing_with(failure))
    fresh = network._Kernels()
    assert fresh.compiled
    monkeypatch.setattr(network, "_kernels", fresh)
    with caplog.at_level(logging.WARNING, logger="core.network"):
        check_against_reference(random_network(2, 16, 100.0), random_points(), SUBSET, 1e-8, 1e-8)
        check_against_reference(random_network(2, 16, 100.0), random_points(), SUBSET, 1e-8, 1e-8)
    assert fresh.fell_back == {
        "first_activation",
        "first_activation_backward",
        "hidden_activation",
        "hidden_activation_backward",
    }
    assert fresh.compiled  # the switch stays on: only the kernels that failed run eagerly
    assert "torch.compile failed" in caplog.text and "simulated" in caplog.text
    assert caplog.text.count("torch.compile failed") == 1


def test_an_error_that_is_not_the_compilers_propagates_and_compiling_stays_on(monkeypatch):
    monkeypatch.setattr(torch, "compile", _compile_failing_with(RuntimeError("a bug in a kernel (simulated)")))
    fresh = network._Kernels()
    monkeypatch.setattr(network, "_kernels", fresh)
    with pytest.raises(RuntimeError, match="a bug in a kernel"):
        random_network(2, 16, 100.0).derivatives(random_points())
    assert fresh.compiled and not fresh.fell_back


@pytest.mark.parametrize("compiled", [False, True])
def test_the_process_switch_selects_eager_or_compiled_kernels(monkeypatch, compiled):
    monkeypatch.setattr(network, "_kernels", network._Kernels())
    network.use_compiled_kernels(compiled)
    assert network._kernels.compiled is compiled
    eager = network._kernels.first_activation is network._first_activation
    assert eager is not compiled
    if not compiled:
        assert network._kernels.hidden_activation_backward is network._hidden_activation_backward


# --- geometric initialisation --------------------------------------------------------------------


def shell_points(n=2000, seed=3, low=0.2, high=0.6):
    """Random directions at radii uniform in [low, high] around the initial sphere (radius 0.4)."""
    generator = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator), dim=1)
    radii = low + (high - low) * torch.rand(n, generator=generator)
    return directions * radii[:, None], directions, radii


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("width, depth", [(256, 4), (64, 2)])
def test_geometric_init_approximates_sphere_sdf(seed, width, depth):
    """At the start f ≈ |x| - 0.4 near the sphere (IGR/SAL initialisation, β = 100).

    The bounds leave room for the init's randomness (about 1/sqrt(width) per layer); a wrong
    weight scale, sign or bias makes the errors several times larger.
    """
    model = ImplicitNetwork(width, depth, beta=100.0, radius=0.4, generator=torch.Generator().manual_seed(seed))
    x, directions, radii = shell_points()
    with torch.no_grad():
        f, grad, _ = model.derivatives(x, laplacian_rows=0)
    error = (f - (radii - 0.4)).abs()
    assert error.mean() < 0.15
    assert error.quantile(0.9) < 0.3
    norm = grad.norm(dim=1)
    assert 0.6 < norm.median() < 1.4
    assert norm.quantile(0.95) < 2.0
    cosine = ((grad / norm[:, None]) * directions).sum(dim=1)
    assert cosine.mean() > 0.85 and cosine.min() > 0.3  # the gradient points away from the centre

    # Along rays from the centre f rises from negative to positive, crossing 0 once near 0.4. The
    # offsets softplus_β(0) = ln 2 / β add up through the layers, so with β = 100 in the unit frame
    # f(0) is about -0.1 to -0.3 rather than -0.4 and the radius varies by direction.
    radii = torch.linspace(0, 1, 101)
    with torch.no_grad():
        along = model((directions[:300, None, :] * radii[None, :, None]).reshape(-1, 3)).reshape(300, 101)
    assert (along[:, :11] < 0).all() and (along[:, 80:] > 0).all()
    assert (along.diff(dim=1) > 0).float().mean() > 0.95
    crossing = radii[(along > 0).float().argmax(dim=1)]
    assert 0.15 <= crossing.min() and crossing.max() <= 0.8 and 0.25 <= crossing.median() <= 0.5


def test_radius_shifts_the_output_bias():
    make = lambda radius: ImplicitNetwork(32, 2, radius=radius, generator=torch.Generator().manual_seed(5))  # noqa: E731
    x, _, _ = shell_points(100)
    with torch.no_grad():
        torch.testing.assert_close(make(0.3)(x) - make(0.4)(x), torch.full((100,), 0.1), rtol=0, atol=1e-6)


@pytest.mark.parametrize("rows", [None, SUBSET, 0], ids=["all", "subset", "none"])
def test_bfloat16_matmuls_stay_close_to_float32(kernels, rows):
    """The training path with bfloat16 matrix products: not exact, but within bfloat16's 3 digits
    of the exact float32 values, and its weight gradients point the same way."""
    model = random_network(4, 64, 100.0, dtype=torch.float32)
    x = random_points(200, dtype=torch.float32)
    exact = model.derivatives(x, rows)
    rough = model.derivatives(x, rows, matmul_dtype=torch.bfloat16)
    # The Laplacian sums larger terms of both signs than f and its gradient do, so it keeps fewer
    # of bfloat16's digits.
    for name, a, b, tolerance in zip(("f", "grad", "laplacian"), exact, rough, (0.02, 0.02, 0.06)):
        if a is None:
            assert b is None
            continue
        error = (a - b).abs().max() / a.abs().max()
        assert 0 < error < tolerance, f"{name}: relative error {error:.2e}"

    def gradients(outputs):
        f, grad, lap = outputs
        loss = f.abs().mean() + (grad.norm(dim=1) - 1).square().mean()
        if lap is not None:
            loss = loss + 1e-3 * lap.square().mean()
        return torch.cat([g.flatten() for g in torch.autograd.grad(loss, list(model.parameters()))])

    cosine = torch.nn.functional.cosine_similarity(gradients(exact), gradients(rough), dim=0)
    assert cosine > 0.995
