"""The implicit function: a softplus MLP and its exact first and second derivatives.

``ImplicitNetwork.derivatives`` returns f, ∇f and Δf in one forward pass ("forward Laplacian"):
every layer carries, besides its activations h, their Jacobian J = ∂h/∂x (three columns) and
their Laplacian L = Δh. Through a linear layer all three are multiplied by the weights (the bias
only touches h); through softplus σ, with z the pre-activation,

    h' = σ(z),   J' = σ'(z) J_z,   L' = σ'(z) L_z + σ''(z) Σ_k (J_z[k])²

The rows [h; J_1; J_2; J_3; L] of a batch are stacked into one matrix, so each layer costs one
matrix product; its backward pass is written out by hand (``_HiddenLayer``), and the element-wise
work on both sides is fused by ``torch.compile`` when a C++ compiler is available (a fit's whole
step, these kernels traced into it, where its shapes are fixed: ``compile_whole``). Rows that need
no Laplacian (a fit's eikonal samples) take ∇f by reverse mode instead (``gradient``), which
multiplies two rows per point through a layer where the forward mode multiplies four.

Everything runs in "β units": softplus_β(z) = softplus(βz)/β, so carrying β·h, β·J and β·L
instead of h, J and L makes every activation a plain softplus(u) with u = βz, and β appears only
in the first layer, the biases and the output. ``derivatives_autograd`` computes f, ∇f and Δf by
nested autograd: the slow, obviously right reference that the tests compare against.
"""

from __future__ import annotations

import copy
import logging
import math
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

log = logging.getLogger(__name__)

# Above u = 40, softplus(u) equals u to within e^-40; below it torch computes log1p(exp(u)).
_SOFTPLUS_THRESHOLD = 40.0


class ImplicitNetwork(nn.Module):
    """A softplus MLP f: R^3 -> R, initialised to approximate the SDF of a sphere.

    ``depth`` hidden layers of ``width`` units with softplus_β activations; geometric
    initialisation (Atzmon & Lipman, SAL) makes f(x) ≈ |x| - radius at the start, negative inside.
    With ``features`` > 0 the first layer reads, besides x, random Fourier features (Tancik et
    al.): sin(b·x) and cos(b·x) for ``features`` directions b drawn with a spread of ``frequency``
    cycles per unit. Each is divided by |b|, so that none rises faster than x does: Adam moves
    every weight by about its learning rate a step, and a feature of amplitude 1 took as much of
    that random walk as x, making every face wavy (the cube's normals 7.9° instead of 2.5°).
    """

    frequencies: Tensor

    def __init__(
        self,
        width: int = 256,
        depth: int = 4,
        beta: float = 100.0,
        radius: float = 0.4,
        generator: torch.Generator | None = None,
        features: int = 0,
        frequency: float = 2.0,
    ):
        super().__init__()
        self.beta = float(beta)
        sizes = [3 + 2 * features] + [width] * depth + [1]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        with torch.no_grad():
            for layer in self.layers[:-1]:
                nn.init.normal_(layer.weight, 0.0, math.sqrt(2.0 / layer.out_features), generator=generator)
                nn.init.zeros_(layer.bias)
            last = self.layers[-1]
            nn.init.normal_(last.weight, math.sqrt(math.pi / last.in_features), 1e-4, generator=generator)
            nn.init.constant_(last.bias, -radius)
            # The Fourier features start with no weight, so that f starts as the same sphere.
            self.layers[0].weight[:, 3:] = 0.0
        # (features, 3): the angular frequencies b of the features sin(b·x)/|b|, cos(b·x)/|b|.
        directions = torch.randn(features, 3, generator=generator)
        self.register_buffer("frequencies", 2 * math.pi * frequency * directions)

    @property
    def features(self) -> int:
        """How many Fourier features the first layer reads (0: x alone)."""
        return len(self.frequencies)

    def _waves(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """sin(b·x)/|b| and cos(b·x)/|b| at the rows of ``x``: each (n, features)."""
        phase = x @ self.frequencies.t()
        amplitude = self.frequencies.norm(dim=1).reciprocal()
        return torch.sin(phase) * amplitude, torch.cos(phase) * amplitude

    def encode(self, x: Tensor) -> Tensor:
        """The first layer's input γ(x) (n, 3 + 2 features): x, sin(b·x)/|b|, cos(b·x)/|b|."""
        if not len(self.frequencies):
            return x
        return torch.cat([x, *self._waves(x)], 1)

    def _encode_stacked(self, x: Tensor) -> Tensor:
        """Stacked rows [γ (n); ∂γ/∂x_k (3n); Δγ (n)] of the encoding at the rows of ``x``:
        ∂ sin(b·x)/∂x_k = cos(b·x) b_k, Δ sin(b·x) = -|b|² sin(b·x)."""
        n = len(x)
        b = self.frequencies
        norm2 = b.square().sum(1)
        sin, cos = self._waves(x)
        eye = torch.eye(3, dtype=x.dtype)
        jac = [torch.cat([eye[k].expand(n, 3), cos * b[:, k], -sin * b[:, k]], 1) for k in range(3)]
        lap = torch.cat([torch.zeros_like(x), -sin * norm2, -cos * norm2], 1)
        return torch.cat([torch.cat([x, sin, cos], 1), *jac, lap])

    def forward(self, x: Tensor) -> Tensor:
        """f at the rows of ``x`` (n, 3): shape (n,)."""
        beta = self.beta
        first, hidden, last = self.layers[0], self.layers[1:-1], self.layers[-1]
        h = _kernels.softplus(F.linear(self.encode(x), first.weight * beta, first.bias * beta))
        for layer in hidden:
            h = _kernels.softplus(F.linear(h, layer.weight, layer.bias * beta))
        return F.linear(h, last.weight / beta, last.bias).squeeze(-1)

    def derivatives(
        self, x: Tensor, laplacian_rows: int | None = None, matmul_dtype: torch.dtype | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """f (n,), ∇f (n, 3) at every row of ``x`` and Δf at its first ``laplacian_rows`` rows.

        ``laplacian_rows=None`` means every row; 0 skips the Laplacian (returned as None). Those
        rows go through the forward Laplacian; the others take f and ∇f from ``gradient``, whose
        products cost half as much per row, forward and backward (a fit's step 14-18 % faster
        where the products dominate, as in float32).
        ``matmul_dtype=torch.bfloat16`` runs the matrix products in bfloat16 (the element-wise work
        stays in the precision of ``x``): several times faster on CPUs with AMX, and accurate
        enough to train with, but no longer exact to float32 rounding. The default is exact.
        """
        n = x.shape[0]
        m = n if laplacian_rows is None else laplacian_rows
        if m == 0:
            f, grad = self.gradient(x, matmul_dtype)
            return f, grad, None
        f, grad, lap = self._forward_laplacian(x[:m], matmul_dtype)
        if m < n:
            f_rest, grad_rest = self.gradient(x[m:], matmul_dtype)
            f, grad = torch.cat([f, f_rest]), torch.cat([grad, grad_rest])
        return f, grad, lap

    def _forward_laplacian(self, x: Tensor, matmul_dtype: torch.dtype | None) -> tuple[Tensor, Tensor, Tensor]:
        """f (n,), ∇f (n, 3) and Δf (n,) at the rows of ``x`` in one forward pass (module doc)."""
        n = x.shape[0]
        beta = self.beta
        dtype = matmul_dtype or x.dtype
        first, hidden, last = self.layers[0], self.layers[1:-1], self.layers[-1]

        weight = first.weight * beta
        if len(self.frequencies):
            # On the encoding, the first layer is a hidden one (in float32: its input is x).
            stacked = _HiddenLayer.apply(self._encode_stacked(x), weight, first.bias * beta, n).to(dtype)
        else:
            # First layer: u = β(W x + b), so its Jacobian is βW for every point and its Laplacian 0.
            u = F.linear(x, weight, first.bias * beta)
            stacked = _FirstLayer.apply(u, weight.t(), dtype)
        for layer in hidden:
            stacked = _HiddenLayer.apply(stacked, layer.weight, layer.bias * beta, n)

        out = (stacked @ last.weight.t().to(dtype)).to(x.dtype).squeeze(-1) / beta
        return out[:n] + last.bias, out[n : 4 * n].view(3, n).t(), out[4 * n :]

    def gradient(self, x: Tensor, matmul_dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
        """f (n,) and ∇f (n, 3) at the rows of ``x`` (n, 3), by reverse mode.

        Carrying the Jacobian forward (``_forward_laplacian``) multiplies four rows per point
        through every layer; going back from f multiplies one, after the forward pass's one, so ∇f
        costs half as much (122,000 points of a default network: 2.7 s against 5.3 s), and is as
        exact. Each layer's slope σ'(u) = sigmoid(u) is kept for the way back (n × width per
        layer). Written in plain operations, so that autograd differentiates it for training:
        its backward multiplies four rows per layer where the forward mode's multiplies eight.
        ``matmul_dtype`` as for ``derivatives``.
        """
        beta = self.beta
        dtype = matmul_dtype or x.dtype
        first, hidden, last = self.layers[0], self.layers[1:-1], self.layers[-1]
        weight = first.weight * beta
        waves = self._waves(x) if len(self.frequencies) else None
        u = F.linear(x if waves is None else torch.cat([x, *waves], 1), weight, first.bias * beta)
        slopes = [torch.sigmoid(u)]
        h = _softplus(u)
        for layer in hidden:
            u = _linear(h, layer.weight, layer.bias * beta, dtype)
            slopes.append(torch.sigmoid(u))
            h = _softplus(u)
        f = _linear(h, last.weight / beta, last.bias, dtype).squeeze(-1)
        # ∂f/∂h of the last hidden layer, then back through each layer: ∂h'/∂h = diag(σ'(u')) W'.
        back = slopes.pop() * (last.weight / beta)
        for layer in reversed(hidden):
            back = _linear(back, layer.weight.t(), None, dtype) * slopes.pop()
        back = back @ weight  # ∂f/∂γ (n, 3 + 2 features)
        if waves is None:
            return f, back
        # Through the encoding: ∂(sin(b·x)/|b|)/∂x = (cos(b·x)/|b|) b, ∂(cos(b·x)/|b|)/∂x = -(sin(b·x)/|b|) b.
        sin, cos = waves
        m = sin.shape[1]
        through = back[:, 3 : 3 + m] * cos - back[:, 3 + m :] * sin
        return f, back[:, :3] + through @ self.frequencies


def _linear(x: Tensor, weight: Tensor, bias: Tensor | None, dtype: torch.dtype) -> Tensor:
    """``F.linear`` with its product in ``dtype`` and its result in ``x``'s."""
    if dtype == x.dtype:
        return F.linear(x, weight, bias)
    out = F.linear(x.to(dtype), weight.to(dtype)).to(x.dtype)
    return out if bias is None else out + bias


def derivatives_autograd(model: ImplicitNetwork, x: Tensor, create_graph: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    """Reference f, ∇f, Δf by nested autograd (slow; for tests and benchmarks).

    f is computed here from the textbook definition, softplus_β(W h + b) layer after layer, so
    that the reference shares no code with the fast paths.
    """
    x = x.detach().requires_grad_(True)
    phase = x @ model.frequencies.t()
    amplitude = 1 / model.frequencies.norm(dim=1)
    h = torch.cat([x, amplitude * torch.sin(phase), amplitude * torch.cos(phase)], 1)
    for layer in model.layers[:-1]:
        h = F.softplus(F.linear(h, layer.weight, layer.bias), model.beta, _SOFTPLUS_THRESHOLD)
    f = F.linear(h, model.layers[-1].weight, model.layers[-1].bias).squeeze(-1)
    (grad,) = torch.autograd.grad(f.sum(), x, create_graph=True)
    lap = torch.zeros_like(f)
    for k in range(3):
        (second,) = torch.autograd.grad(grad[:, k].sum(), x, create_graph=create_graph)
        lap = lap + second[:, k]
    return f, grad, lap


class _FirstLayer(torch.autograd.Function):
    """The first layer's activation on pre-activations u (n, d), given its Jacobian (3, d) = βW^T:
    stacked rows [h (n); J (3n); L (n)], with the backward written out as for ``_HiddenLayer``.
    Left to autograd, the compiled forward and backward took twice as long (3.9 against 1.9 ms at
    512 points: autograd's version of the broadcast Jacobian and its sums over the rows)."""

    @staticmethod
    def forward(ctx, u: Tensor, jacobian: Tensor, dtype: torch.dtype) -> Tensor:
        ctx.save_for_backward(u, jacobian)
        return _kernels.first_activation(u, jacobian, dtype)

    @staticmethod
    def backward(ctx, grad_stacked: Tensor):
        u, jacobian = ctx.saved_tensors
        grad_u, grad_jacobian = _kernels.first_activation_backward(grad_stacked, u, jacobian, len(u))
        return grad_u, grad_jacobian, None


class _HiddenLayer(torch.autograd.Function):
    """One hidden layer on stacked rows [h (n); J (3n); L (n)], with its backward written out.

    ``bias`` is already multiplied by β; the stacked state is in β units (see the module doc).
    The matrix products run in the stacked state's dtype, the element-wise work in the bias's.
    """

    @staticmethod
    def forward(ctx, stacked: Tensor, weight: Tensor, bias: Tensor, n: int) -> Tensor:
        out = stacked @ weight.t().to(stacked.dtype)
        result, u = _kernels.hidden_activation(out, bias, n)
        ctx.save_for_backward(stacked, weight, out, u)
        ctx.n = n
        return result

    @staticmethod
    def backward(ctx, grad_result: Tensor):
        stacked, weight, out, u = ctx.saved_tensors
        grad_out, grad_bias = _kernels.hidden_activation_backward(grad_result, out, u, ctx.n)
        grad_stacked = grad_out @ weight.to(out.dtype) if ctx.needs_input_grad[0] else None
        grad_weight = (grad_out.t() @ stacked).to(weight.dtype)
        return grad_stacked, grad_weight, grad_bias, None


# --- element-wise kernels (β = 1), fused by torch.compile when it works -------------------------


def _softplus(u: Tensor) -> Tensor:
    return F.softplus(u, 1.0, _SOFTPLUS_THRESHOLD)


def _first_activation(u: Tensor, jacobian: Tensor, dtype: torch.dtype) -> Tensor:
    """Stacked [h; J; L] after the first layer, in ``dtype``: u (n, d) pre-activations, jacobian (3, d) = βW^T."""
    s = torch.sigmoid(u)
    h = F.softplus(u, 1.0, _SOFTPLUS_THRESHOLD)
    jac = s.unsqueeze(0) * jacobian.unsqueeze(1)
    lap = s * (1 - s) * jacobian.square().sum(0)
    return torch.cat([h, jac.reshape(-1, u.shape[1]), lap]).to(dtype)


def _first_activation_backward(grad: Tensor, u: Tensor, jacobian: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """The gradients with respect to u (n, d) and the Jacobian (3, d), given that of [h; J; L]:
    h = σ₁(u), J_k = σ(u) a_k, L = σ(u)(1 - σ(u)) Σ_k a_k² with a = ``jacobian``."""
    grad = grad.to(u.dtype)
    s = torch.sigmoid(u)
    t = s * (1 - s)  # σ''
    grad_jac = grad[n : 4 * n].view(3, n, -1)
    grad_lap = grad[4 * n :]
    grad_u = grad[:n] * s + t * (grad_jac * jacobian.unsqueeze(1)).sum(0)
    grad_u = grad_u + grad_lap * t * (1 - 2 * s) * jacobian.square().sum(0)
    grad_jacobian = (grad_jac * s).sum(1) + 2 * jacobian * (grad_lap * t).sum(0)
    return grad_u, grad_jacobian


def _hidden_activation(out: Tensor, bias: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Softplus on stacked pre-activations ``out`` = [u - bias; J_u; L_u]; returns [h; J; L] and u.

    Computes in the bias's precision and returns the stacked result in ``out``'s dtype.
    """
    u = out[:n].to(bias.dtype) + bias
    s = torch.sigmoid(u)
    jac_u = out[n : 4 * n].view(3, n, -1).to(bias.dtype)
    lap = s * out[4 * n :].to(bias.dtype) + s * (1 - s) * jac_u.square().sum(0)
    return torch.cat([F.softplus(u, 1.0, _SOFTPLUS_THRESHOLD), (s * jac_u).view(3 * n, -1), lap]).to(out.dtype), u


def _hidden_activation_backward(grad: Tensor, out: Tensor, u: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """The gradient with respect to the stacked pre-activations (in ``out``'s dtype) and the bias,
    given that of [h; J; L]."""
    grad = grad.to(u.dtype)
    s = torch.sigmoid(u)
    t = s * (1 - s)  # σ''
    jac_u = out[n : 4 * n].view(3, n, -1).to(u.dtype)
    lap_u = out[4 * n :].to(u.dtype)
    grad_jac = grad[n : 4 * n].view(3, n, -1)
    grad_lap = grad[4 * n :]
    grad_u = grad[:n] * s + t * (grad_jac * jac_u).sum(0)
    grad_u = grad_u + grad_lap * (t * lap_u + t * (1 - 2 * s) * jac_u.square().sum(0))
    grad_jac_u = grad_jac * s + 2 * grad_lap * t * jac_u
    return torch.cat([grad_u, grad_jac_u.view(3 * n, -1), grad_lap * s]).to(out.dtype), grad_u.sum(0)


class _Kernels:
    """The element-wise kernels, and the functions compiled whole (``compile_whole``), compiled on
    first use unless compiling is off; eager otherwise.

    ``core.runtime.configure`` sets ``compiled`` for the process. A kernel whose compilation fails
    in the compiler backend (no C++ compiler, an unsupported platform) runs eagerly from then on,
    and the first such failure is logged; any other error is a bug in the kernel and propagates.
    A thread inside ``eager_kernels`` gets the eager kernels; any other thread waits for a
    background warm-up (``warm_kernels_in_background``) before it calls a compiled kernel, so that
    two threads never compile at once.
    """

    _eager: ClassVar[dict[str, Callable[..., Any]]] = {
        "softplus": _softplus,
        "first_activation": _first_activation,
        "first_activation_backward": _first_activation_backward,
        "hidden_activation": _hidden_activation,
        "hidden_activation_backward": _hidden_activation_backward,
    }

    def __init__(self, compiled: bool = True):
        self.compiled = compiled
        self.fell_back: set[str] = set()  # the kernels whose compilation failed
        self._functions: dict[str, Callable[..., Any]] = {}
        self.thread_state = threading.local()  # .eager: this thread runs the eager kernels
        self.warm_up: _WarmUp | None = None

    # Compiled for one shape of their arguments each (``compile_whole``): a whole step, whose
    # autograd Functions torch.compile traces for fixed shapes only.
    _static: ClassVar[set[str]] = set()

    def __getattr__(self, name: str) -> Callable[..., Any]:
        eager = self._eager[name]
        if torch.compiler.is_compiling():  # inside a whole compiled function: traced into it
            return eager
        if not self.compiled or name in self.fell_back or getattr(self.thread_state, "eager", False):
            return eager
        if self.warm_up is not None and self.warm_up is not threading.current_thread():
            self.finish_warm_up()
        if name not in self._functions:
            if name in self._static:
                # A whole step's graph holds the autograd Functions' forward and backward as traced
                # subgraphs, so the graph itself keys the autograd cache; let it use that cache,
                # which torch leaves off for such graphs: loading a fit's three steps from the
                # disk took 12.3 s without it, 6.4 s with it.
                from torch._functorch import config as functorch_config  # loaded by torch.compile anyway

                functorch_config.autograd_cache_allow_custom_autograd_functions = True
            self._functions[name] = torch.compile(eager, dynamic=name not in self._static)
        compiled = self._functions[name]
        from torch._dynamo.exc import BackendCompilerFailed  # loaded by torch.compile already

        def call(*args: Any) -> Any:
            try:
                return compiled(*args)
            except BackendCompilerFailed as error:
                if not self.fell_back:
                    log.warning("torch.compile failed (%s); running the eager kernels", error)
                self.fell_back.add(name)
                return eager(*args)

        return call

    def finish_warm_up(self) -> None:
        """Wait for the background warm-up, if one runs, then raise its error if it had one."""
        warm_up, self.warm_up = self.warm_up, None
        if warm_up is None:
            return
        warm_up.join()
        if warm_up.error is not None:
            raise warm_up.error


class _WarmUp(threading.Thread):
    """A thread that calls every compiled kernel a fit and its extraction will call, on a few rows
    of a copy of the fit's network, so that the kernels are compiled (or loaded from the disk
    cache) while the fit's first steps run eagerly. An error in it is raised by
    ``_Kernels.finish_warm_up``."""

    def __init__(
        self,
        network: ImplicitNetwork,
        matmul_dtype: torch.dtype | None,
        laplacian: bool,
        steps: Callable[[ImplicitNetwork], None] | None,
    ):
        super().__init__(name="kernel-warm-up", daemon=True)
        self.network, self.matmul_dtype, self.laplacian, self.steps = network, matmul_dtype, laplacian, steps
        self.error: BaseException | None = None
        self.switch_interval = sys.getswitchinterval()

    def run(self) -> None:
        try:
            x = torch.rand(12, 3, generator=torch.Generator().manual_seed(0)) - 0.5
            if self.steps is not None:  # the fit's whole steps, compiled for its shapes
                self.steps(self.network)
            else:
                f, grad, lap = self.network.derivatives(x, 4 if self.laplacian else 0, self.matmul_dtype)
                (f.sum() + grad.sum() + (lap.sum() if lap is not None else 0)).backward()
            with torch.no_grad():  # the extraction's calls
                self.network(x)
                self.network.derivatives(x)
        except BaseException as error:  # handed to the thread that waits
            self.error = error
        finally:
            sys.setswitchinterval(self.switch_interval)


_kernels = _Kernels()

# The interpreter's switch interval while a warm-up runs (``warm_kernels_in_background``).
WARM_UP_SWITCH_INTERVAL = 1e-5


def compile_whole(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` compiled whole, as the kernels are (when compiling is on, outside
    ``eager_kernels``, after a background warm-up, eagerly after a compiler failure), for each
    shape of its arguments it meets.

    For a training step: compiled whole, its forward and backward are a few fused kernels between
    the matrix products instead of hundreds of operator calls (the default step at 512 points
    14.2 → 10.1 ms on a Xeon with AMX, ``bench/run.py --only step-parts``). The kernels it calls
    are traced into it."""
    name = function.__name__
    _Kernels._eager[name] = function
    _Kernels._static.add(name)

    def call(*args: Any) -> Any:
        return getattr(_kernels, name)(*args)

    return call


def use_compiled_kernels(enabled: bool) -> None:
    """Compile the element-wise kernels (True, the default) or run them eagerly, for the whole process."""
    _kernels.compiled = enabled


def warm_kernels_in_background(
    network: ImplicitNetwork,
    matmul_dtype: torch.dtype | None,
    laplacian: bool,
    steps: Callable[[ImplicitNetwork], None] | None = None,
) -> None:
    """Compile the kernels that a fit of ``network`` (on a copy of it) with these
    options will call, in a background thread; a no-op when compiling is off or a warm-up runs.
    ``steps``, when given, takes the fit's steps of every shape it will take on the copy (its
    whole steps compiled, ``compile_whole``) in place of the training's kernels one by one.

    Compiled kernels take 5-9 s to load from the disk cache and 30 s or more to compile after an
    install; the fit's first steps run the eager kernels meanwhile (``eager_kernels``).
    """
    if not _kernels.compiled or _kernels.warm_up is not None:
        return
    # Imported here, before the thread starts: the fit's optimizer imports it at its first step
    # anyway, and the two threads importing the compiler's modules at once can each hold one the
    # other needs (an ImportError of a partially initialised torch._dynamo module, seen in a test).
    import torch._dynamo  # noqa: F401

    _kernels.warm_up = _WarmUp(copy.deepcopy(network), matmul_dtype, laplacian, steps)
    # Both threads want the interpreter's lock: the compiler for its tracing, the fit for each
    # operation's dispatch. Handed over every 10 µs instead of 5 ms, the first step came after
    # 3.2-4.0 s instead of 4.9 s (the set-up waited for the lock too).
    sys.setswitchinterval(WARM_UP_SWITCH_INTERVAL)
    _kernels.warm_up.start()


def finish_warming_kernels() -> None:
    """Wait for a background warm-up (``warm_kernels_in_background``), if one runs."""
    _kernels.finish_warm_up()


@contextmanager
def eager_kernels() -> Iterator[None]:
    """Run the eager kernels in this thread inside the block, whether or not compiling is on."""
    state = _kernels.thread_state
    before = getattr(state, "eager", False)
    state.eager = True
    try:
        yield
    finally:
        state.eager = before
