"""Stage-1 training (paper Eq. s1): trainer, losses, schedule, checkpoints, metrics, progress bar."""
