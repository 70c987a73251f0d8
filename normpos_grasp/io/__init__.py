"""File formats: BOP datasets, point clouds (PLY), JSON results."""
