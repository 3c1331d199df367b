"""Build hook (the rest of the build is in pyproject.toml): the training configs of the
repository's `configs/` folder ship inside the `ued` package as `ued/data/configs/`, where
`ued.config_files` finds them by name (`tabx train quickstart`). They stay at the top of the
repository so that `tabx train configs/...` paths work in a checkout.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

CONFIGS = Path(__file__).resolve().parent / "configs"


class BuildPyWithConfigs(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):  # it reads the checkout's configs/ in place
            return
        target = Path(self.build_lib) / "ued" / "data" / "configs"
        for source in sorted(CONFIGS.rglob("*.yaml")):
            destination = target / source.relative_to(CONFIGS)
            destination.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, destination)


setup(cmdclass={"build_py": BuildPyWithConfigs})
