"""2D teachers for stage 1: dense feature maps and depth priors per training image (cached on disk)."""
