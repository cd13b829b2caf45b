"""Loaders for pretrained networks (Stable Diffusion, CLIP), from local paths only; nothing is fetched from a hub."""
