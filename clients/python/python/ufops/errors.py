"""The exceptions ufops raises. Bad arrays and arguments raise ``TypeError`` (dtype, type) or
``ValueError`` (shape, value); everything else is a :class:`UfopsError`::

    UfopsError
    ├── ArtifactError        an artifact that is malformed or does not fit this client
    │   └── IntegrityError   a file whose sha256 is not the manifest's, corrupt store data
    ├── FetchError           talking to ``ufops serve`` failed (connection, HTTP status)
    │   └── AuthError        401 / 403: the token is missing, wrong or lacks the role
    ├── NotFoundError        an unknown artifact, alias, episode, split or version
    ├── StoreError           the catalog or the object storage failed
    └── ConflictError        a label changed since it was read (``Client.set_label``)
"""
from __future__ import annotations

from typing import Optional

from ufops._ufops import (
    ArtifactError,
    AuthError,
    FetchError,
    IntegrityError,
    NotFoundError,
    StoreError,
    UfopsError,
)

__all__ = [
    "UfopsError",
    "ArtifactError",
    "IntegrityError",
    "FetchError",
    "AuthError",
    "NotFoundError",
    "StoreError",
    "ConflictError",
]


class ConflictError(UfopsError):
    """A write lost a race: the label changed since it was read (HTTP 409).

    ``actor``, ``revision``, ``label`` and ``at`` say who changed it, to what, and when (as the
    API reports them; ``None`` when it did not).
    """

    def __init__(
        self,
        message: str,
        *,
        actor: Optional[str] = None,
        revision: Optional[int] = None,
        label: Optional[str] = None,
        at: Optional[str] = None,
    ) -> None:
        super().__init__(message)
        self.actor = actor
        self.revision = revision
        self.label = label
        self.at = at
