"""``meshseq blender-addon``: write the Blender add-on (meshseq/blender_addon/) as an installable zip."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

#: the add-on's module name inside the zip (Blender's Preferences > Add-ons lists it as "meshseq")
ADDON_MODULE = "meshseq_blender"
_DEFAULT_LINE = 'DEFAULT_MESHSEQ = "meshseq"'


def register(sub) -> None:
    p = sub.add_parser("blender-addon", help="write the Blender add-on as a zip to install in Blender",
                       description="Write the meshseq add-on for Blender (3.4 and later) as a zip: install it "
                       "with Edit > Preferences > Add-ons > Install, enable it, and find it in the 3D view's "
                       "sidebar (N), tab meshseq. It trains, completes between timeline markers, predicts and "
                       "samples by running this meshseq command in a subprocess.")
    p.add_argument("-o", "--output", default="meshseq_addon.zip", metavar="ZIP",
                   help="the zip to write (default meshseq_addon.zip)")
    p.add_argument("--meshseq", default=None, metavar="PATH",
                   help="the meshseq command the add-on runs by default (default: this one, "
                   "by its absolute path; changeable in the add-on's preferences)")
    p.add_argument("--force", action="store_true", help="overwrite ZIP if it exists")
    p.set_defaults(func=cmd_blender_addon)


def this_meshseq() -> str:
    """The absolute path of the running meshseq command (the console script beside this Python,
    else the one on PATH), or ``meshseq`` if neither exists."""
    beside = Path(sys.executable).parent / ("meshseq.exe" if os.name == "nt" else "meshseq")
    if beside.is_file():
        return str(beside.absolute())
    return shutil.which("meshseq") or "meshseq"


def addon_files(meshseq_path: str) -> dict[str, str]:
    """The zip's files (name -> text): the add-on (``addon.py`` as the package's ``__init__.py``,
    with ``meshseq_path`` as its default meshseq command) and ``cachefiles.py``."""
    from importlib.resources import files

    from meshseq.errors import MeshseqError

    folder = files("meshseq") / "blender_addon"
    text = (folder / "addon.py").read_text(encoding="utf-8")
    if text.count(_DEFAULT_LINE) != 1:
        raise MeshseqError("the installed add-on source lacks its DEFAULT_MESHSEQ line; reinstall meshseq")
    return {f"{ADDON_MODULE}/__init__.py": text.replace(_DEFAULT_LINE, f"DEFAULT_MESHSEQ = {meshseq_path!r}"),
            f"{ADDON_MODULE}/cachefiles.py": (folder / "cachefiles.py").read_text(encoding="utf-8")}


def cmd_blender_addon(args) -> int:
    import zipfile

    from meshseq.errors import MeshseqError
    from meshseq.io import atomic_output

    if Path(args.output).suffix.lower() != ".zip":
        raise MeshseqError(f"-o {args.output}: Blender installs add-ons from a .zip; give a path ending in .zip")
    exe = args.meshseq or this_meshseq()
    contents = addon_files(exe)
    with atomic_output(args.output, force=args.force) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, text in contents.items():
                zf.writestr(name, text)
    print(f"wrote {args.output}: install it in Blender (Edit > Preferences > Add-ons > Install), enable "
          f"'meshseq', then 3D view > sidebar (N) > meshseq; it runs {exe}")
    return 0
