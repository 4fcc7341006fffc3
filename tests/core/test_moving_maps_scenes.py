"""bench.moving_maps names a scene by its class and seed: which other classes run beside it does
not change it (scene 200 of one run was another room than scene 200 of another, before)."""

from __future__ import annotations

from bench.moving_maps import scenes


def test_a_scene_depends_on_its_class_and_seed_only():
    for seed in (0, 3):
        alone = {name: scenes(seed, [name]) for name in ("rgbd", "robot", "tls")}
        together = scenes(seed, ["robot", "rgbd", "tls"])
        for name, mine in alone.items():
            assert [scene for scene in together if scene[0] == name] == mine
        for mine in alone.values():
            seeds = [scene[-1] for scene in mine]
            assert len(set(seeds)) == len(seeds)
            assert all(100 * seed <= value < 100 * (seed + 1) for value in seeds)


def test_rgbd_rooms_keep_the_seeds_of_the_rgbd_only_runs():
    # the figures in bench/results/moving_maps.md for --classes rgbd stay comparable
    assert [scene[-1] for scene in scenes(2, ["robot", "rgbd"]) if scene[0] == "rgbd"] == [
        200,
        201,
        202,
        203,
        204,
    ]
