"""YAML documents from outside, loaded with bounds: a damaged or hostile file is a
:class:`ConfigError` naming the file and the fix, never a hang or a memory exhaustion.

The load is bounded twice: the file size and the size of the document with every alias
expanded. PyYAML shares an aliased node instead of copying it, so a 1 kB "billion laughs"
loads at once into a few shared lists; it is the first conversion to an array
(``np.array(matrix)``) that expands it (7.45 GiB for a nine-level bomb). Counting the
expanded nodes on the composed graph (memoised, linear in the file) refuses it before
anything is built, and still reads a file that uses an alias or two.

Documents are parsed and written by libyaml (:data:`SAFE_LOADER`, :func:`dump_yaml`)
when PyYAML has it: a real-size calibration.yaml (4 MB, 12 000 poses of two set-ups) is
read in 2.5 s instead of 13 s and written in 1.4 s instead of 5.9 s, the same document.
Composing still costs microseconds a node (PyYAML builds a Python object for each), and a
node can cost as little as two bytes (``[0,0,0,…]``): 8 MiB of such rows took 65 s to
compose in pure Python and 19 s with libyaml. A caller that knows how many nodes its
largest honest document has passes ``max_items``: every node but the root is introduced
by an indicator (``- ``, ``:``, ``,``, ``[``, ``{``, ``?``), so twice their count bounds
the nodes, counted on the text before it is parsed (:func:`indicator_count`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from kpi_calib_ros.core.errors import ConfigError

# A calibration.yaml of 10 000 measurements is ~2 MB (its residuals); 32 MiB is far above
# any real document and bounds the pure-Python parse to seconds.
MAX_DOCUMENT_BYTES = 32 * 2 ** 20
# Scalars and collections of the document with every alias expanded: ~10 per measurement
# (residuals, training poses), so a million measurements fit.
MAX_DOCUMENT_NODES = 10_000_000
FIX = 'give a calibration.yaml written by kpi-calib identify (unedited)'
# libyaml's safe loader and dumper when PyYAML was built with it (the PyPI wheels are),
# else the pure-Python ones; both read and write the same documents.
SAFE_LOADER: type[yaml.SafeLoader] = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
SAFE_DUMPER: type[yaml.SafeDumper] = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


def dump_yaml(doc: Any) -> str:
    """``doc`` (safe types) as YAML text, keys in their order (:data:`SAFE_DUMPER`)."""
    return yaml.dump(doc, Dumper=SAFE_DUMPER, sort_keys=False)


def indicator_count(text: str) -> int:
    """The YAML indicators in ``text`` that may introduce a node (``- `` and ``-`` before a
    tab or line end, ``:``, ``,``, ``[``, ``{``, ``?``): a document has at most twice this
    many nodes plus one (its root), whatever its style. Counted in C, milliseconds a MiB."""
    return (text.count('- ') + text.count('-\n') + text.count('-\t') + text.count('-\r')
            + sum(text.count(c) for c in ':,[{?'))


def load_yaml_bounded(text: str, where: str, key: str, fix: str = FIX,
                      loader: type[yaml.SafeLoader] = SAFE_LOADER,
                      max_bytes: int = MAX_DOCUMENT_BYTES,
                      max_nodes: int = MAX_DOCUMENT_NODES,
                      max_items: int | None = None) -> Any:
    """The YAML document ``text`` (safe types only), refused when larger than
    ``max_bytes``, with more than ``max_items`` indicators (:func:`indicator_count`;
    None: not counted), or, with its aliases expanded, more than ``max_nodes`` nodes, or
    recursive.

    Parameters
    ----------
    text : str
        The document.
    where : str
        The file it came from, for messages.
    key : str
        The ConfigError key (the option or setting that named the file).
    fix : str
        What the user should give instead, ending each message (default: a calibration
        written by ``kpi-calib identify``, the document most read back).
    loader : yaml.SafeLoader subclass
        E.g. the cell loader with its YAML 1.2 float rule.
    """
    size = len(text.encode('utf-8', 'surrogatepass'))
    if size > max_bytes:
        raise ConfigError(key, f'{where} is {size} bytes, more than the {max_bytes} bytes '
                          f'such a document may have; {fix}')
    if max_items is not None:
        items = indicator_count(text)
        if items > max_items:
            raise ConfigError(key, f'{where} has {items} YAML items (entries, keys and '
                              f'values), more than the {max_items} such a document may have; '
                              f'{fix}')
    # The loader checks the characters as it is built (a control character, e.g. a NUL
    # byte of a damaged disk, is a ReaderError there): built inside the try.
    reader = None
    try:
        reader = loader(text)
        node = reader.get_single_node()
        if node is None:
            return None
        nodes = _expanded_nodes(node, key, where, fix, max_nodes)
        if nodes > max_nodes:
            raise ConfigError(key, f'{where}: its YAML aliases (*name) expand to more than '
                              f'{max_nodes} nodes; {fix}')
        return reader.construct_document(node)
    except yaml.reader.ReaderError as exc:
        raise ConfigError(key, f'{where} holds a character YAML does not allow ('
                          f'#x{exc.character:04x}, a control character, at character '
                          f'{exc.position}): the file is damaged or not text; {fix}') from None
    except yaml.YAMLError as exc:
        raise ConfigError(key, f'{where} is not valid YAML: {exc}; {fix}') from None
    except RecursionError:
        raise ConfigError(key, f'{where} nests deeper than YAML can be read; {fix}') from None
    finally:
        if reader is not None:
            reader.dispose()


def read_yaml_file(path: str | Path, key: str, fix: str,
                   loader: type[yaml.SafeLoader] = SAFE_LOADER,
                   max_bytes: int = MAX_DOCUMENT_BYTES,
                   max_nodes: int = MAX_DOCUMENT_NODES,
                   max_items: int | None = None) -> Any:
    """The YAML document in ``path`` (which must exist), its size checked before it is
    read, then loaded as :func:`load_yaml_bounded`; unreadable files (permissions, not
    UTF-8) are a ConfigError naming ``key``, the file and ``fix``."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise ConfigError(key, f'{path} is {size} bytes, more than the {max_bytes} bytes '
                              f'such a document may have; {fix}')
        text = path.read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(key, f'cannot read {path}: {exc}; {fix}') from None
    return load_yaml_bounded(text, str(path), key, fix, loader, max_bytes, max_nodes,
                             max_items)


def _expanded_nodes(root: yaml.Node, key: str, where: str, fix: str, max_nodes: int) -> int:
    """Number of nodes of ``root`` with every alias (a shared node) counted each time it
    is used; stops counting above the limit. Iterative, memoised by node."""
    done: dict[int, int] = {}
    open_: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        ident = id(node)
        if ident in done:
            continue
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        if children_done:
            total = 1 + sum(done[id(c)] for c in children)
            done[ident] = min(total, max_nodes + 1)
            open_.discard(ident)
            continue
        if ident in open_:
            raise ConfigError(key, f'{where}: a YAML alias refers to itself (a recursive '
                              f'document); {fix}')
        open_.add(ident)
        stack.append((node, True))
        for child in children:
            if id(child) in open_:
                raise ConfigError(key, f'{where}: a YAML alias refers to itself (a '
                                  f'recursive document); {fix}')
            if id(child) not in done:
                stack.append((child, False))
    return done[id(root)]


__all__ = ['FIX', 'MAX_DOCUMENT_BYTES', 'MAX_DOCUMENT_NODES', 'indicator_count',
           'load_yaml_bounded', 'read_yaml_file']
