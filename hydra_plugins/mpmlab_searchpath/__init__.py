"""Hydra search-path plugin: makes config groups shipped by mpmlab plugin packages selectable.

A plugin package declares, next to its law/scene entry points,

    [project.entry-points."mpmlab.configs"]
    my_laws = "my_laws.conf"        # a Python package holding Hydra config groups (material/, scene/, ...)

and this plugin appends ``pkg://my_laws.conf`` to Hydra's config search path, so that
``mpmlab material=<their material>`` works and ``mpmlab --info searchpath`` lists
``mpmlab-plugin:my_laws``. Hydra finds this module by scanning the ``hydra_plugins`` namespace
package (Hydra does not read entry points itself); ``mpmlab.cli`` also registers it explicitly, so
it works under every kind of editable install.
"""
from __future__ import annotations

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


def plugin_config_paths() -> list[tuple[str, str]]:
    """``(provider, "pkg://module")`` for every ``mpmlab.configs`` entry point, sorted by name."""
    from importlib.metadata import entry_points

    out = []
    for ep in sorted(entry_points(group="mpmlab.configs"), key=lambda e: e.name):
        module = ep.value.split(":", 1)[0].strip()
        out.append((f"mpmlab-plugin:{ep.name}", f"pkg://{module}"))
    return out


class MpmlabSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        present = {element.path for element in search_path.get_path()}
        for provider, path in plugin_config_paths():
            if path not in present:  # idempotent: scanned and explicitly registered are the same class
                search_path.append(provider=provider, path=path)
                present.add(path)
