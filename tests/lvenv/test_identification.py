"""The one parameter space: unit-cube maps on NumPy and JAX, log axes, narrowed bounds, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, ParameterSpace


def test_log_axes_are_log_uniform_and_linear_axes_uniform():
    space = ParameterSpace.for_names(("tau2", "R2"))
    u = np.array([[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]])
    x = space.from_unit(u)
    np.testing.assert_allclose(x[:, 0], [0.05, np.sqrt(0.05 * 0.6), 0.6], rtol=1e-14)  # geometric mean at u = 0.5
    np.testing.assert_allclose(x[:, 1], [0.0, 0.025, 0.05], rtol=1e-14)
    np.testing.assert_allclose(space.to_unit(x), u, atol=1e-15)


def test_numpy_and_jax_maps_agree_inside_jit():
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    u = np.random.default_rng(0).random((5, space.dimension))
    x_np = space.from_unit(u)
    x_jax = jax.jit(space.from_unit)(jnp.asarray(u))
    assert isinstance(x_jax, jax.Array)
    np.testing.assert_allclose(np.asarray(x_jax), x_np, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(jax.jit(space.to_unit)(x_jax)), u, atol=1e-13)
    assert np.all(x_np >= np.array(space.lower)) and np.all(x_np <= np.array(space.upper))


def test_narrowed_bounds_and_parts():
    space = ParameterSpace.for_names(("C", "Sa"), {"C": (5.0, 20.0)})
    assert space.lower == (5.0, ACTION_BOUNDS["Sa"].lo) and space.upper == (20.0, ACTION_BOUNDS["Sa"].hi)
    assert space.parts == ("circulation", "cell") and space.units == ("ml/kPa", "1")
    assert hash(space) == hash(ParameterSpace.for_names(("C", "Sa"), {"C": (5.0, 20.0)}))


@pytest.mark.parametrize(
    "names, bounds, message",
    [
        (("tau3",), None, "'tau3' has no identification bounds"),
        ("tau2", None, "sequence of names"),
        (("tau2", "tau2"), None, "repeat"),
        ((), None, "at least one"),
        (("C",), {"C": (20.0, 5.0)}, "lower must be below upper"),
        (("C",), {"C": (0.5, 5.0)}, r"lower bound of C = 0.5 must be a finite real number in \[1, 30\]"),
        (("C",), {"C": ("a", 5.0)}, "lower bound of C = 'a'"),
        (("C",), {"C": 5.0}, "must be a pair"),
        (("C",), {"Sa": (0.5, 1.0)}, "not among the parameters"),
    ],
)
def test_bad_spaces_are_named(names, bounds, message):
    with pytest.raises(ValueError, match=message):
        ParameterSpace.for_names(names, bounds)


def test_rate_is_the_derivative_of_the_unit_cube_map():
    import numpy as np

    from lvenv.identification import ParameterSpace

    space = ParameterSpace.for_names()
    u = np.random.default_rng(2).uniform(0.05, 0.95, (5, space.dimension))
    step = 1e-6
    numeric = (space.from_unit(u + step) - space.from_unit(u - step)) / (2 * step)
    np.testing.assert_allclose(space.rate(space.from_unit(u)), numeric, rtol=1e-6)
