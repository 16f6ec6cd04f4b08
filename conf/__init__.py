"""Hydra configs of torchrl-stages (installed as the package ``torchrl_stages.conf``)."""
