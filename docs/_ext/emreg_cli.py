"""The ``{cli}`` role: an ``emreg`` command line written in the manual's prose, checked against the parser.

``{cli}`emreg run CASE --out OUT``` renders as code and links to that command in the generated command line
reference. Every subcommand and every option it names must exist in ``EMRegModule.cli.main.build_parser()``;
otherwise the build warns, and since ``scripts/test`` builds with ``-W``, a renamed or removed option that the
prose still mentions fails the tests. The ``emreg`` lines of the manual's shell code blocks (``bash``, ``console``,
``sh``, ``shell``) are checked the same way.
"""

from __future__ import annotations

import argparse
import re

from docutils import nodes
from sphinx import addnodes
from sphinx.util import logging

logger = logging.getLogger(__name__)
_PARSERS: dict[str, argparse.ArgumentParser] = {}


def _parsers() -> dict[str, argparse.ArgumentParser]:
    """``""`` -> the top-level parser, each subcommand's name -> its parser (made once per build)."""
    if not _PARSERS:
        from EMRegModule.cli.main import build_parser

        parser = build_parser()
        _PARSERS[""] = parser
        for action in parser._actions:  # argparse keeps the subcommands in a _SubParsersAction
            if isinstance(action, argparse._SubParsersAction):
                _PARSERS.update(action.choices)
    return _PARSERS


def problems(text: str) -> tuple[str, list[str]]:
    """The subcommand a command line names (``""`` for none) and what in it the parser does not know."""
    parsers = _parsers()
    words = [w for w in re.split(r"[\s\[\]|]+", text) if w]
    if words and words[0] == "emreg":
        words = words[1:]
    command = ""
    found = []
    if words and not words[0].startswith("-"):
        if words[0] not in parsers:
            return "", [f"no emreg subcommand {words[0]!r}"]
        command = words[0]
    known = parsers[command]._option_string_actions
    for word in words:
        if word.startswith("-") and len(word) > 1 and not word[1].isdigit():
            option = word.split("=", 1)[0].rstrip(",.;:)")
            if option not in known:
                found.append(f"emreg {command + ' ' if command else ''}has no option {option}")
    return command, found


def cli_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    """Render an emreg command line as code linked to its command in the reference; warn on unknown names."""
    command, found = problems(text)
    for problem in found:
        logger.warning("{cli}`%s`: %s (see EMRegModule.cli.main.build_parser)", text, problem,
                       location=(inliner.document.settings.env.docname, lineno))
    literal = nodes.literal(rawtext, text, classes=["cli"])
    if found:
        return [literal], []
    target = f"emreg {command}" if command else "emreg"
    xref = addnodes.pending_xref(rawtext, refdomain="commands", reftype="command", reftarget=target,
                                 refexplicit=True, refwarn=True)
    xref += literal
    return [xref], []


SHELL_LANGUAGES = {"bash", "console", "sh", "shell"}


def check_code_blocks(app, doctree) -> None:
    """Warn about every ``emreg`` command line of a shell code block that the parser does not know."""
    for block in doctree.findall(nodes.literal_block):
        if block.get("language") not in SHELL_LANGUAGES:
            continue
        text = block.astext().replace("\\\n", " ")  # a command continued on the next line is one command
        for line in text.splitlines():
            command = line.split(" #", 1)[0].strip().removeprefix("$ ")
            if command.startswith("emreg ") or command == "emreg":
                for problem in problems(command)[1]:
                    logger.warning("code block line %r: %s (see EMRegModule.cli.main.build_parser)", command, problem,
                                   location=block)


def setup(app):
    app.add_role("cli", cli_role)
    app.connect("doctree-read", check_code_blocks)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
