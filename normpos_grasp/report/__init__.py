"""Pictures and 3D views of a cell's frame: overlay PNG, GLB digital twin, self-contained HTML viewer, live view."""
