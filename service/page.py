"""The web page (``GET /``) and its static files (``/static``): submit a cloud, watch it, look at the result.

Everything the page needs is in ``service/static/`` (plain HTML, CSS and ES modules, and three.js
vendored in ``static/vendor/three``): no build step and no outside address. The page talks to the
API like any client (``/openapi.json`` for its form, ``/v1`` for jobs), so it needs no server code
beyond serving these files. Neither route needs the API key (the page asks for it and sends it to
``/v1`` itself), and neither appears in the OpenAPI schema.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from starlette.staticfiles import StaticFiles

STATIC = Path(__file__).resolve().with_name("static")

router = APIRouter(include_in_schema=False)


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    """The page itself; revalidated on every load, so a new version shows at once."""
    return FileResponse(STATIC / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})


router.mount("/static", StaticFiles(directory=STATIC), name="static")
