"""Scene loaders, one module per dataset format; `detect.load_scene` picks the right one."""
