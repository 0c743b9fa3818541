"""Motion files for other tools: BVH (:mod:`.bvh`) and C3D (:mod:`.c3d`). Domain library: no orchestration."""
