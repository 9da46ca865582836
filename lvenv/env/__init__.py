"""Gymnasium environments over the LO heart: ``lvenv/LVHeart-v0`` (single and vector)."""

from lvenv.env.single import LVHeartEnv
from lvenv.env.vector import LVHeartVectorEnv

__all__ = ["LVHeartEnv", "LVHeartVectorEnv", "register"]

ENV_ID = "lvenv/LVHeart-v0"


def register() -> None:
    """Register ``lvenv/LVHeart-v0`` (entry point and vector entry point); idempotent."""
    import gymnasium

    if ENV_ID not in gymnasium.registry:
        gymnasium.register(
            id=ENV_ID,
            entry_point="lvenv.env.single:LVHeartEnv",
            vector_entry_point="lvenv.env.vector:LVHeartVectorEnv",
            max_episode_steps=200,
        )
