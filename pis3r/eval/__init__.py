"""Evaluation: the paper's protocol, image-quality and geometry metrics, peer baselines."""
