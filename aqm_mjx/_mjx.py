"""MJX, imported quietly.

``mujoco.mjx`` prints "Failed to import warp" lines on stdout when the optional ``warp`` package is
absent. That is noise for users who do not ask for ``impl='warp'``, so the import goes through here.
"""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()) as _import_log:
    from mujoco import mjx  # noqa: E402

#: What MJX printed while importing (kept for ``impl='warp'`` error messages).
IMPORT_LOG: str = _import_log.getvalue()


def warp_available() -> bool:
    """Whether MuJoCo Warp can be used as an MJX implementation here."""
    try:
        from mujoco.mjx._src import io as _io  # pylint: disable=import-outside-toplevel
        return bool(getattr(_io.mjxw, 'WARP_INSTALLED', False))
    except Exception:  # pragma: no cover - depends on the optional install
        return False


__all__ = ['mjx', 'IMPORT_LOG', 'warp_available']
