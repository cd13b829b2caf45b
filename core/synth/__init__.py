"""Synthetic scenes with ground truth (depth, object masks, an edited variant), rendered with moderngl.

Entry points: `core.synth.generate.make_scene`, `list_presets`, and `core.synth.demo.demo_scene_path`.
"""
