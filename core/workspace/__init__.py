"""What is saved per scene: settings, checkpoints, teacher caches, selections, masks, versions (atomic writes)."""
