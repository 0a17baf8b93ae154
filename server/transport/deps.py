"""FastAPI dependencies: the session manager, and the session a request's token opens."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Header, Request

from server.sessions import Session, SessionManager
from server.settings import Settings


def get_manager(request: Request) -> SessionManager:
    return request.app.state.manager


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def bearer_token(authorization: Annotated[str | None, Header()] = None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    if authorization is None:
        return None
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def authorized_session(
    session_id: str,
    manager: Annotated[SessionManager, Depends(get_manager)],
    token: Annotated[str | None, Depends(bearer_token)],
) -> Session | dict:
    """The live Session, or a closed session's saved meta, that the token opens."""
    return manager.authorize(session_id, token)


ManagerDep = Annotated[SessionManager, Depends(get_manager)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
SessionDep = Annotated[Session | dict, Depends(authorized_session)]
