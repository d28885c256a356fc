"""``/``: a page that shows the live channels and plots the right bank's back-pressure."""

from importlib.resources import files

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

router = APIRouter(tags=["page"])


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def page() -> str:
    return files("service").joinpath("static/index.html").read_text()
