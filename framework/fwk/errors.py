"""Errors a user sees. Anything that is an FwkError is the user's to fix (a recipe key, a file,
a topology) and is printed as one sentence without a traceback; everything else is a bug."""


class FwkError(Exception):
    """A user-facing error: one sentence that names the thing to fix."""


class RecipeError(FwkError):
    """A recipe key, value or component name is wrong. The message starts with the key path."""


class PluginError(FwkError):
    """A plugin could not be loaded, or two plugins register the same name."""


class UnknownComponentError(RecipeError):
    """A recipe names a component that no plugin registers."""


class DataError(FwkError):
    """A mesh file or dataset is missing, unreadable or inconsistent. The message names the file."""


class TopologyError(DataError):
    """A mesh does not share the template's topology. The message names the file and what differs."""


class PathError(FwkError):
    """A folder the user gave (``--runs-dir``, ``$FWK_RUNS_DIR``, ``$FWK_CACHE``, ``--out``) cannot
    take the output: not a folder, a file in the way, not writable, no space. Names the path."""


class WriteError(FwkError, OSError):
    """A file could not be written for a reason the user can fix (no space, a quota, a file-size
    limit, permissions). Also an ``OSError`` (with its ``errno``), so callers that tolerate write
    failures (the cache) still do."""

    def __str__(self):
        return str(self.strerror) if self.strerror else super().__str__()


class Terminated(BaseException):
    """The process received SIGTERM (``kill``, a job scheduler's time limit) while ``fwk run``
    ran: raised where the process was, so that the run marks itself ``FAILED`` before it ends.
    A BaseException, like KeyboardInterrupt, so that no ``except Exception`` swallows it."""


#: the most characters of a user's value an error message quotes (``quote``)
QUOTE_LIMIT = 200


def quote(value, limit: int = QUOTE_LIMIT) -> str:
    """``repr(value)`` for an error message, cut to about ``limit`` characters (a recipe value or
    a key can be megabytes long: the message stays one short line)."""
    try:
        text = repr(value)
    except Exception:  # a value whose repr fails (or recurses) is named by its type
        text = f"<{type(value).__name__}>"
    return cut(text.replace("\n", "\\n").replace("\r", "\\r"), limit)


def cut(text: str, limit: int = QUOTE_LIMIT) -> str:
    """``text`` cut to ``limit`` characters, saying how long it was (``quote`` without the repr:
    a recipe key in a key path)."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"
