"""The one renderer: occupancy grid, ray marching with empty-space skipping, stable compositing."""
