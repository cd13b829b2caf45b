"""Structure-from-motion on folders of photos (pycolmap): intake, pipeline, cached runner."""
