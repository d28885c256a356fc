"""``/``: the live dashboard (plots, channel table, tuning, scripts), and its static files.

The page talks only to the public HTTP API; its scripts are this project's own
(``service/static``), served at ``/static/NAME``.
"""

from importlib.resources import files

from fastapi import APIRouter, HTTPException
from fastapi.responses import HTMLResponse, Response

router = APIRouter(tags=["page"])
STATIC = {"plot.js": "text/javascript", "dashboard.js": "text/javascript", "dashboard.css": "text/css"}


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def page() -> str:
    return files("service").joinpath("static/index.html").read_text()


@router.get("/static/{name}", include_in_schema=False)
def static(name: str) -> Response:
    if name not in STATIC:
        raise HTTPException(404, detail=f"no static file {name!r}")
    text = files("service").joinpath("static", name).read_text()
    return Response(text, media_type=STATIC[name], headers={"Cache-Control": "no-cache"})
