"""instant-ngp's fixed sample batch (TrainConfig.samples_per_batch): a step takes the rays whose samples fill the
batch at the recent samples per ray, within [rays_per_batch / min_rays_divisor, rays_per_batch]."""
from __future__ import annotations

from repaint_nerf.core.scene.loaders.detect import load_scene
from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig


def test_rays_per_step_follow_the_samples_per_ray(scene_factory):
    scene = load_scene(scene_factory("demo", size=16, views=6))
    tr = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=256, samples_per_batch=256 * 8,
                                                grid_resolution=16, max_samples=32))
    assert tr.rays_now() == 256  # nothing marched yet: the full batch
    for spr, rays in ((2.0, 256), (8.0, 256), (16.0, 128), (64.0, 32), (1000.0, 32)):
        tr.recent_samples_per_ray = spr
        assert tr.rays_now() == rays
    tr.recent_samples_per_ray = None
    info = tr.step()  # a foggy field marches every step of its budget: more than 8 per ray, so fewer rays follow
    assert info["rays"] == 256 and info["samples_per_ray"] > 8.0
    assert tr.recent_samples_per_ray == info["samples_per_ray"]
    assert tr.step()["rays"] == int(256 * 8 / info["samples_per_ray"])
    fixed = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=256, samples_per_batch=0,
                                                   grid_resolution=16, max_samples=32))
    fixed.step()
    assert fixed.step()["rays"] == 256
