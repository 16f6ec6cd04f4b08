"""The package list, found rather than listed: ``torchrl_stages`` and its sub-packages, and
``envs/`` and ``conf/`` (at the top of the repository) with theirs, installed as
``torchrl_stages.envs`` and ``torchrl_stages.conf``. Everything else is in pyproject.toml."""

from setuptools import find_packages, setup


def under(package: str, where: str) -> list[str]:
    """``package`` (the folder ``where``) and every sub-package of it."""
    return [package, *(f"{package}.{sub}" for sub in find_packages(where))]


setup(
    packages=[
        *find_packages(include=["torchrl_stages", "torchrl_stages.*"]),
        *under("torchrl_stages.envs", "envs"),
        *under("torchrl_stages.conf", "conf"),
    ]
)
