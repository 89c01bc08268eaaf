"""Dataset augmentation: in-between shapes, linear and simulated with a flesh model."""
