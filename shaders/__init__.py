"""shaders package."""
