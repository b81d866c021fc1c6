"""Old name of :mod:`hec_jax.mjx_scene.render` (kept while ``experiments/hand_eye.py`` and
``tests/test_hand_eye.py`` import it; remove it once they import from ``render``)."""

from hec_jax.mjx_scene.render import SceneCamera, render_model_like

__all__ = ["SceneCamera", "render_model_like"]
