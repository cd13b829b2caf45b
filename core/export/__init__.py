"""Exports that take a result out of the editor: meshes and point clouds (world units), an edited dataset in the
nerfstudio / instant-ngp layout, H.264 videos and GIFs, and nerfstudio camera paths. One module per kind; every
file is written to a temporary name and renamed, so a killed export never leaves a half-written file."""
