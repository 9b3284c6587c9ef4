"""Whether every package that a distribution needs at run time is installed at a version it
accepts: its Requires-Dist, followed through each dependency's own, markers evaluated and
extras left out. Run after an offline install (scripts/offline_install.sh), where pip was told
not to resolve dependencies: a package that one of the bundled wheels needs but that neither
the bundle nor the machine has (typer 0.29 needs pydantic, say) is named here, before a run
reaches the import that needs it.

    python scripts/check_requirements.py [DISTRIBUTION]      # twist by default

Prints one line per unmet requirement and exits 1 if there is any, else prints "ok".
"""

from __future__ import annotations

import sys
from importlib import metadata

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name


def unmet_requirements(root: str = "twist") -> list[str]:
    """Each requirement in ``root``'s run-time closure that no installed version satisfies, as
    ``"<needed by>: <requirement> (<what is installed>)"``; [] when all are met."""
    unmet: list[str] = []
    seen: set[str] = set()
    pending = [root]
    while pending:
        name = pending.pop()
        key = canonicalize_name(name)
        if key in seen:
            continue
        seen.add(key)
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue  # reported by whoever required it (or the root's own check below)
        for text in requires:
            requirement = Requirement(text)
            if requirement.marker is not None and not requirement.marker.evaluate({"extra": ""}):
                continue
            try:
                installed = metadata.version(requirement.name)
            except metadata.PackageNotFoundError:
                unmet.append(f"{name}: {requirement} (not installed)")
                continue
            if not requirement.specifier.contains(installed, prereleases=True):
                unmet.append(f"{name}: {requirement} ({installed} installed)")
            pending.append(requirement.name)
    return unmet


def main(argv: list[str]) -> int:
    root = argv[1] if len(argv) > 1 else "twist"
    try:
        metadata.version(root)
    except metadata.PackageNotFoundError:
        print(f"{root} is not installed")
        return 1
    unmet = unmet_requirements(root)
    for line in unmet:
        print(line)
    if not unmet:
        print("ok")
    return 1 if unmet else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
