"""Hostile-input checks of a recipe, run before the schema and before any work.

One mechanism each, for every field at once (not per-field checks):

* :func:`load_yaml_strict`: YAML → document, refusing texts above :data:`MAX_RECIPE_BYTES`,
  duplicate mapping keys (YAML would keep the last one silently), alias expansion beyond
  :data:`MAX_ALIAS_NODES` nodes (a 400-byte "billion laughs" text expands to 10⁹ nodes) and
  recursive aliases.
* :func:`value_problems`: one walk over the parsed document that refuses every number that is not
  finite (NaN, ±inf: JSON Schema range checks are false for NaN, so NaN would pass them), integers
  that do not fit a float, and control characters in strings (``description`` may hold newlines and
  tabs), each with its field path.

Sizes of tables and strings are limited in the schema (``maxItems``, ``maxLength``,
flakedb/schemas/recipe.schema.json); the limits are restated here so messages and tests can name them.
"""

from __future__ import annotations

import math
import re
import unicodedata

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode, ScalarNode, SequenceNode

from flakedb.paint.limits import NODE_COUNT_MAX
from flakedb.safeio import FileTooLargeError, read_limited

#: Largest recipe text [bytes]: a recipe with every table at its schema limit is far below it.
MAX_RECIPE_BYTES = 1_000_000
#: Largest number of nodes that aliases (``*name``) may expand to in one recipe.
MAX_ALIAS_NODES = 10_000
#: Largest magnitude of an integer in a recipe (it must be exact as a float64).
MAX_INT = 2 ** 53
#: Node count limit of ``resolution`` / ``--n`` (:data:`flakedb.paint.limits.NODE_COUNT_MAX`).
MAX_RESOLUTION = NODE_COUNT_MAX
#: Entries per tabulated spectrum / flake table / phase table (the schema's ``maxItems``).
MAX_TABLE_POINTS = 10_000
#: Characters of ``description`` (the schema's ``maxLength``).
MAX_DESCRIPTION_CHARS = 10_000
#: Keys whose strings may hold line breaks and tabs.
MULTILINE_KEYS = ("description",)


class RecipeInputError(ValueError):
    """A recipe text refused before parsing finished: ``problem`` is one line."""

    def __init__(self, problem):
        self.problem = problem
        super().__init__(problem)


def _mark(m):
    return f"line {m.line + 1}, column {m.column + 1}" if m is not None else "?"


def _node_size(node, sizes, busy):
    """Nodes of ``node`` with every alias expanded (memoised by identity; recursion → inf)."""
    k = id(node)
    if k in sizes:
        return sizes[k]
    if k in busy:
        return math.inf
    busy.add(k)
    if isinstance(node, ScalarNode):
        n = 1
    elif isinstance(node, SequenceNode):
        n = 1 + sum(_node_size(v, sizes, busy) for v in node.value)
    else:
        n = 1 + sum(_node_size(a, sizes, busy) + _node_size(b, sizes, busy) for a, b in node.value)
    busy.discard(k)
    sizes[k] = n
    return n


#: libyaml's parser and composer when present (6x faster than the pure-Python ones), else PyYAML's.
_BASE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class StrictLoader(_BASE_LOADER):
    """A safe loader that refuses duplicate mapping keys (merge keys ``<<`` excepted)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, MappingNode):
            seen = {}
            for key_node, _ in node.value:
                if not isinstance(key_node, ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                if key in seen:
                    raise ConstructorError(None, None, f"duplicate key {key!r} (first at {_mark(seen[key])}); "
                                           f"each key may appear once (YAML would keep the last one silently)",
                                           key_node.start_mark)
                seen[key] = key_node.start_mark
        return super().construct_mapping(node, deep)


def _alias_problem(root):
    """None, or why the composed document ``root`` is refused: aliases expanding it by more than
    :data:`MAX_ALIAS_NODES` nodes, or an alias inside the collection it names (recursion)."""
    sizes = {}
    expanded = _node_size(root, sizes, set())
    if expanded == math.inf:
        return "an alias (*name) refers to the collection that contains it (recursive structures are refused)"
    if expanded - len(sizes) > MAX_ALIAS_NODES:
        return (f"aliases (*name) expand the recipe by {expanded - len(sizes):,.0f} nodes, more than the limit of "
                f"{MAX_ALIAS_NODES:,} (hint: write the values out instead of nesting aliases)")
    return None


def load_yaml_strict(text, limit=MAX_RECIPE_BYTES):
    """Parse recipe ``text``: raises :class:`RecipeInputError` for a text above the size limit, an
    alias bomb or a recursive alias (checked on the composed node graph, before anything is
    expanded), ``yaml.YAMLError`` (with a mark) for syntax errors and duplicate keys.

    A duplicate key, which plain YAML would silently overwrite, and a recursive alias are refused:

    >>> load_yaml_strict("name: a")
    {'name': 'a'}
    >>> load_yaml_strict('''
    ... name: a
    ... name: b
    ... ''')
    Traceback (most recent call last):
    ...
    yaml.constructor.ConstructorError: duplicate key 'name' (first at line 2, column 1); each key may appear once ...
    >>> load_yaml_strict("a: &x [1, *x]")
    Traceback (most recent call last):
    ...
    flakedb.paint.checks.RecipeInputError: an alias (*name) refers to the collection that contains it (recursive structures are refused)
    """
    size = len(text.encode("utf-8", errors="surrogatepass")) if isinstance(text, str) else len(text)
    if size > limit:
        raise RecipeInputError(too_large_message(size) if limit == MAX_RECIPE_BYTES else
                               f"the text is {size:,} bytes; the limit is {limit:,} bytes")
    loader = StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        problem = _alias_problem(node)
        if problem:
            raise RecipeInputError(problem)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def too_large_message(size):
    return (f"the recipe is {size:,} bytes; the limit is {MAX_RECIPE_BYTES:,} bytes "
            f"(hint: a recipe is a short YAML file; tabulate spectra with fewer points)")


def _path(parts):
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


#: Unicode's control characters (general category Cc): U+0000–U+001F and U+007F–U+009F.
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def _string_problem(parts, key, s):
    """The control-character problem of string ``s`` at path ``parts`` (its key ``key``), or None."""
    if _CONTROL.search(s) is None:  # the usual string: one scan in C, no path formatted
        return None
    path = _path(parts)
    allowed = "\n\t" if key in MULTILINE_KEYS else ""
    for i, ch in enumerate(s):
        if unicodedata.category(ch) == "Cc" and ch not in allowed:
            return (f"{path}: contains the control character U+{ord(ch):04X} at position {i}; control characters "
                    f"(line breaks included{', except in a description' if not allowed else ''}) are refused "
                    f"(hint: remove it; check for a trailing newline)")
    return None


def value_problems(doc, limit=20) -> list[str]:
    """Every non-finite number, over-large integer and misplaced control character in ``doc``,
    as ``path: message`` (at most ``limit``: the rest are of the same kind)."""
    out = []
    stack = [((), None, doc)]
    while stack and len(out) < limit:
        parts, key, v = stack.pop()
        if isinstance(v, bool) or v is None:
            continue
        if isinstance(v, float):
            if not math.isfinite(v):
                out.append(f"{_path(parts)}: value {v} is not a finite number (NaN and infinity are refused "
                           f"everywhere) (hint: give a finite number)")
        elif isinstance(v, int):
            if abs(v) > MAX_INT:
                out.append(f"{_path(parts)}: integer with {len(str(abs(v)))} digits is outside the allowed "
                           f"range |value| ≤ 2^53 (hint: give a physical value)")
        elif isinstance(v, str):
            p = _string_problem(parts, key, v)
            if p:
                out.append(p)
        elif isinstance(v, dict):
            for k, x in reversed(list(v.items())):
                if isinstance(k, str):
                    p = _string_problem(parts + (k,), None, k)
                    if p:
                        out.append(p.replace(": contains", ": the key contains", 1))
                        continue
                stack.append((parts + (k,), k, x))
        elif isinstance(v, list):
            for i in reversed(range(len(v))):
                stack.append((parts + (i,), key, v[i]))
    return out


class YamlFileError(ValueError):
    """A YAML file that cannot be read as a document: ``problem`` is one line (without the path)."""

    def __init__(self, path, problem):
        self.path = path
        self.problem = problem
        super().__init__(f"{path}: {problem}")


def load_yaml_file(path, what="recipe", limit=MAX_RECIPE_BYTES):
    """The one way flakedb reads a YAML file the user names (recipes, match bases, ``--catalog`` files):
    a regular file only (:mod:`flakedb.safeio`: no FIFO, device or socket, a symlink only to a regular
    file), at most ``limit`` bytes read, UTF-8, then :func:`load_yaml_strict` (duplicate keys, alias
    bombs and recursive aliases refused).  Raises :class:`YamlFileError` naming the problem, with the
    line and column of a syntax error."""
    try:
        text = read_limited(path, limit).decode("utf-8")
    except FileNotFoundError:
        raise YamlFileError(path, "no such file") from None
    except FileTooLargeError as exc:
        raise YamlFileError(path, f"the {what} file is {exc.size:,} bytes or more; the limit is {limit:,} bytes "
                                  f"(hint: a {what} is a short YAML file)") from None
    except UnicodeDecodeError as exc:
        raise YamlFileError(path, f"not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except OSError as exc:
        raise YamlFileError(path, f"cannot read the file ({exc.strerror or exc})") from None
    return text, parse_yaml_text(text, path, limit)


def parse_yaml_text(text, source="<yaml>", limit=MAX_RECIPE_BYTES):
    """:func:`load_yaml_strict` with every failure as a :class:`YamlFileError` (one line, with the
    line and column of a syntax error)."""
    try:
        return load_yaml_strict(text, limit)
    except RecipeInputError as exc:
        raise YamlFileError(source, exc.problem) from None
    except RecursionError:
        raise YamlFileError(source, "YAML nesting is too deep (hint: a recipe nests a few levels)") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "?"
        raise YamlFileError(source, f"YAML syntax error at {where}: {getattr(exc, 'problem', exc)}") from None
    except (ValueError, TypeError, OverflowError) as exc:  # a scalar the safe constructor cannot build (a date 2024-13-45)
        raise YamlFileError(source, f"YAML value error: {exc}") from None
