"""Parameters of the phantom pipeline; defaults are the numbers of Nagy & Benedek's paper."""

from __future__ import annotations

from pydantic import BaseModel, Field

from app.core.bounds import Count, Metres, ObjectMetres, Resolution, Share, Threads


class PhantomConfig(BaseModel):
    cell_size: Resolution = Field(0.2, description="s_c: pillar base, metres")
    pillar_height: Metres = Field(3.0, gt=0, description="pillars reach this high above ground")
    voxel_size: Resolution = Field(0.1, description="voxel edge: 2 x 2 x 30 voxels per pillar")
    neighbourhood: int = Field(
        11, ge=3, le=101, description="pillars per side of the CNN window (11 x 11)"
    )
    refine_window: int = Field(5, ge=1, le=51, description="N: Algorithm 1 neighbourhood (5 x 5)")
    refine: bool = True
    ground_cell: Resolution = Field(1.0, description="metres: cells of the ground-height estimate")
    ground_opening: int = Field(5, ge=1, le=101, description="cells: objects narrower not ground")
    ground_tolerance: ObjectMetres = Field(
        0.15, ge=0, description="points this close above the ground stay ground (DESIGN.md)"
    )
    min_object_points: Count = Field(
        3, ge=0, description="pillars with fewer points above ground_tolerance are ground"
    )
    below_ground: ObjectMetres = Field(
        0.3, ge=0, description="points this far below ground still count"
    )
    prior_weight: Share = Field(
        1.0, description="w: weight of the map's class priors (priors.py), 0 = paper"
    )
    tile_pillars: int = Field(
        32, ge=8, le=4096, description="dense inference tile size (output pillars)"
    )
    batch_size: int = Field(
        512, ge=1, le=65_536, description="windows per batch on the per-window path"
    )
    threads: Threads = Field(0, description="torch threads, 0 = all cores")

    @property
    def voxels_per_cell(self) -> int:
        return round(self.cell_size / self.voxel_size)

    @property
    def voxels_high(self) -> int:
        """Voxels per pillar column (30); at most 32, they share a packed key with x and y."""
        n = round(self.pillar_height / self.voxel_size)
        if n > 32:
            raise ValueError(f"pillar_height / voxel_size = {n} voxels: at most 32 are supported")
        return n

    @property
    def window_voxels(self) -> int:
        return self.neighbourhood * self.voxels_per_cell
