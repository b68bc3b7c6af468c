"""Pure-numpy geometry: rigid transforms, camera projection, pillar grid, voxels, trajectory."""
