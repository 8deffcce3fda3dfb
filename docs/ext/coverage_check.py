"""MkDocs hook: fail the build if a public name has no entry on an API page.

The public surface is the ``__all__`` of the modules in ``PUBLIC``. A name is
documented when a ``::: identifier`` directive of a page under ``docs/api/`` renders
it: the directive names the object itself, or a module whose members it renders
(a module directive without ``members: false`` renders the names of its
``__all__``). Objects are compared by identity, so ``nhjax.scenes.Skate`` is
covered by ``::: nhjax.scenes.skate``. A public name that is a module is covered
when that module has a directive of its own or is itself in ``PUBLIC``.
"""

from __future__ import annotations

import importlib
import re
import types

from mkdocs.exceptions import PluginError

PUBLIC = [
    "nhjax",
    "nhjax.scenes",
    "nhjax.mechanics",
    "nhjax.mechanics.reduction",
    "nhjax.lie",
    "nhjax.lie.so3",
    "nhjax.lie.se2",
    "controls",
    "controls.tasks",
    "controls.distributed",
    "nhjax.integrate.distributed",
]

_DIRECTIVE = re.compile(r"^::: +([\w.]+)[ \t]*\n((?:[ \t]+.*\n?)*)", re.MULTILINE)

_documented: dict[int, str] = {}


def _resolve(identifier: str):
    parts = identifier.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(identifier)


def on_pre_build(config):
    _documented.clear()


def on_page_markdown(markdown, page, config, files):
    if not page.file.src_uri.startswith("api/"):
        return markdown
    for identifier, options in _DIRECTIVE.findall(markdown):
        obj = _resolve(identifier)
        _documented[id(obj)] = identifier
        if isinstance(obj, types.ModuleType) and not re.search(r"^\s*members:\s*false", options, re.MULTILINE):
            for name in getattr(obj, "__all__", ()):
                _documented.setdefault(id(getattr(obj, name)), f"{identifier}.{name}")
    return markdown


def on_post_build(config):
    missing = []
    for module_name in PUBLIC:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if id(obj) in _documented:
                continue
            if isinstance(obj, types.ModuleType) and obj.__name__ in PUBLIC:
                continue
            missing.append(f"{module_name}.{name}")
    if missing:
        raise PluginError("public names without an entry on an API page (docs/api/*.md; "
                          "add a '::: name' directive): " + ", ".join(missing))
