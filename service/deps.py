"""Dependencies shared by the routers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from cell.app.cell import Cell


def get_cell(request: Request) -> Cell:
    return request.app.state.cell


CellDep = Annotated[Cell, Depends(get_cell)]
