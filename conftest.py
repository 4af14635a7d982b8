"""Doctests of the package's docstring examples: the names the examples use."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import volshade


@pytest.fixture(autouse=True)
def _doctest_names(doctest_namespace):
    doctest_namespace.update(jax=jax, jnp=jnp, np=np, eqx=eqx, volshade=volshade, vs=volshade)
