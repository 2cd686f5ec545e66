"""core.params.FitParams: the paper's defaults, bounds, types and form-style coercion.

Bounds are read from the model itself, so the tests follow them when they change; only the
defaults the paper fixes are written out here.
"""

from __future__ import annotations

import math

import annotated_types
import pytest
from pydantic import ValidationError

from core.params import FitParams

FIELDS = FitParams.model_fields
NUMERIC = [name for name, field in FIELDS.items() if field.annotation in (int, float)]


def bounds(name: str) -> dict[str, float]:
    """{'ge' | 'gt' | 'le' | 'lt': value} of a field."""
    found = {}
    for item in FIELDS[name].metadata:
        for key in ("ge", "gt", "le", "lt"):
            if isinstance(item, getattr(annotated_types, key.capitalize())):
                found[key] = getattr(item, key)
    return found


def rejected(**values) -> list[dict]:
    with pytest.raises(ValidationError) as info:
        FitParams(**values)
    return info.value.errors()


def test_shipped_defaults():
    """The paper's λ1 and DES; λ2, τ and the robust penalty as measured best (docs/benchmarks.md)."""
    params = FitParams()
    assert params.lambda1 == 0.1
    assert (params.lambda2, params.tau, params.laplacian_penalty) == (1e-4, 30.0, "robust")
    assert params.edge_sampling is True


def test_the_papers_variant_is_selectable():
    params = FitParams(lambda2=0.001, tau=20, laplacian_penalty="quadratic")
    assert (params.lambda2, params.tau, params.laplacian_penalty, params.edge_sampling) == (
        0.001,
        20.0,
        "quadratic",
        True,
    )


def test_every_default_is_valid_and_documented():
    params = FitParams()
    assert FitParams(**params.model_dump()) == params
    assert FitParams.model_validate_json(params.model_dump_json()) == params
    for name in NUMERIC:
        value, limits = getattr(params, name), bounds(name)
        assert limits, f"{name} has no bounds"
        assert {"ge", "gt"} & limits.keys() and {"le", "lt"} & limits.keys(), name
        assert value >= limits.get("ge", -math.inf) and value > limits.get("gt", -math.inf), name
        assert value <= limits.get("le", math.inf) and value < limits.get("lt", math.inf), name
    for name, field in FIELDS.items():
        assert field.description, f"{name} has no description (the CLI's --help uses it)"


@pytest.mark.parametrize("name", NUMERIC)
def test_bounds_are_enforced(name):
    limits = bounds(name)
    annotation = FIELDS[name].annotation

    def beyond(limit: float, sign: int) -> float:
        return limit + sign * (1 if annotation is int else max(abs(limit) * 1e-6, 1e-9))

    if "ge" in limits:
        FitParams(**{name: limits["ge"]})
        errors = rejected(**{name: beyond(limits["ge"], -1)})
        assert errors[0]["loc"] == (name,) and errors[0]["type"] == "greater_than_equal"
    if "gt" in limits:
        errors = rejected(**{name: limits["gt"]})
        assert errors[0]["loc"] == (name,) and errors[0]["type"] == "greater_than"
    if "le" in limits:
        FitParams(**{name: limits["le"]})
        errors = rejected(**{name: beyond(limits["le"], +1)})
        assert errors[0]["loc"] == (name,) and errors[0]["type"] == "less_than_equal"
    errors = rejected(**{name: -(10**9)})
    assert errors[0]["loc"] == (name,)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "nan", "inf", "-Infinity"])
@pytest.mark.parametrize("name", [n for n in NUMERIC if FIELDS[n].annotation is float])
def test_non_finite_floats_are_rejected(name, value):
    errors = rejected(**{name: value})
    assert errors[0]["loc"] == (name,) and errors[0]["type"] == "finite_number"


@pytest.mark.parametrize("name", [n for n in NUMERIC if FIELDS[n].annotation is int])
def test_non_finite_and_fractional_ints_are_rejected(name):
    for value in (math.nan, math.inf, 2.5, "2.5"):
        assert rejected(**{name: value})[0]["loc"] == (name,)


def test_unknown_fields_are_rejected():
    errors = rejected(lambda_1=0.5)
    assert errors[0]["loc"] == ("lambda_1",) and errors[0]["type"] == "extra_forbidden"
    assert rejected(tau=10, Tau=10)[0]["loc"] == ("Tau",)


@pytest.mark.parametrize(
    "name, value",
    [
        ("iterations", "many"),
        ("iterations", [100]),
        ("iterations", None),
        ("lambda1", "0.1.2"),
        ("lambda2", {"value": 0.001}),
        ("tau", None),
        ("edge_sampling", "maybe"),
        ("edge_sampling", 2),
        ("edge_sampling", None),
        ("resolution", "64px"),
        ("seed", b"\xff"),
    ],
)
def test_wrong_types_are_rejected(name, value):
    assert rejected(**{name: value})[0]["loc"] == (name,)


@pytest.mark.parametrize("name", ["iterations", "lambda1"])
def test_booleans_are_not_numbers(name):
    rejected(**{name: True})


def test_form_strings_are_coerced():
    """A multipart form sends every field as a string."""
    params = FitParams(
        iterations="20", lambda1="0.5", lambda2="1e-4", tau="20", edge_sampling="true", resolution="64", seed="7"
    )
    assert (params.iterations, params.resolution, params.seed) == (20, 64, 7)
    assert (params.lambda1, params.lambda2, params.tau) == (0.5, 1e-4, 20.0)
    assert params.edge_sampling is True
    assert isinstance(params.iterations, int) and isinstance(params.tau, float)
    for text, expected in [("true", True), ("false", False), ("1", True), ("0", False), ("on", True), ("off", False)]:
        assert FitParams(edge_sampling=text).edge_sampling is expected


def test_params_are_immutable():
    params = FitParams()
    with pytest.raises(ValidationError):
        params.tau = 5.0
    assert params.tau == FitParams().tau
    assert hash(params) == hash(FitParams())
