"""The output files of a reconstruction: their names, and the one way to write them to disk.

No torch here: the API names the outputs too.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path

# What a job of the service stores (and lists in its links once it succeeded).
OUTPUT_NAMES = ("mesh.obj", "normals.json", "edges.json", "preview.json")
# What ``edgerecon fit`` writes unless told otherwise (preview.json is for the web page's view).
FIT_OUTPUTS = ("mesh.obj", "normals.json", "edges.json")
# The most input points preview.json holds: the web page draws them all and stays responsive.
PREVIEW_POINTS = 50_000
# The mesh's formats (``mesh.<format>``; ``core.mesh_formats`` makes them): jobs store the OBJ.
MESH_FORMATS = ("obj", "ply", "stl", "glb")


def write_atomically(files: Mapping[str, bytes], directory: str | os.PathLike[str]) -> Path:
    """Write ``files`` (name to content) into ``directory`` so that a failure leaves no partial
    folder or file; return the folder.

    The files are written into a staging folder beside ``directory``, which is then renamed to it
    (or, when ``directory`` exists, each file is moved into it with an atomic rename).
    """
    directory = Path(directory).resolve()
    directory.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}-", dir=directory.parent))
    umask = os.umask(0)
    os.umask(umask)
    staging.chmod(0o777 & ~umask)  # mkdtemp makes it private; the output folder should not be
    try:
        for name, content in files.items():
            (staging / name).write_bytes(content)
        if not directory.exists():
            staging.rename(directory)
            return directory
        for name in files:
            os.replace(staging / name, directory / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return directory
