"""Capture sessions: the session.yaml layout shared by simulate, capture, sync and convert."""

from .layout import SESSION_FORMAT, SESSION_FORMAT_VERSION, Session, ViewRecord, load_session

__all__ = ["SESSION_FORMAT", "SESSION_FORMAT_VERSION", "Session", "ViewRecord", "load_session"]
