"""Test-wide setup: importing lvenv first enables float64 before any test builds arrays."""

import lvenv  # noqa: F401
