"""kdrt.Error: every failure of a kdrt call, shaped like the C++ client's kdrt::Error."""

from __future__ import annotations

import json

from http import HTTPStatus

#: Error.kind values (the C++ client's ErrorKind names).
KINDS = ("server", "connection", "protocol", "input", "job_failed", "cancelled")


class Error(Exception):
    """A failed call.

    kind:        "server" (the server answered 4xx/5xx; the problem+json fields below are its),
                 "connection" (no answer: cannot connect, connection lost or timed out, after
                 the retries), "protocol" (a 2xx answer the API does not allow), "input" (a
                 local argument is unusable), "job_failed", "cancelled".
    status:      the HTTP status (0 when there was no answer).
    title, detail, type, code, request_id: the problem+json members (or a fixed phrase and the
                 URL, file or value for the local kinds).
    line, byte_offset, limit, retry_after: problem members when the server sent them (mesh parse
                 errors carry `line` for text formats and `byte_offset` for binary ones).
    problem:     the whole problem+json object as a dict ({} when the answer had none).
    attempts:    requests sent for this call (1 + retries).
    """

    def __init__(self, kind="server", status=0, title="", detail="", type="", code="",
                 request_id="", line=None, byte_offset=None, limit=None, retry_after=None,
                 problem=None, attempts=1):
        self.kind = kind
        self.status = status
        self.title = title
        self.detail = detail
        self.type = type
        self.code = code
        self.request_id = request_id
        self.line = line
        self.byte_offset = byte_offset
        self.limit = limit
        self.retry_after = retry_after
        self.problem = problem or {}
        self.attempts = attempts
        super().__init__(str(self))

    def __str__(self):
        if self.kind == "server":
            return f"{self.status} {self.title}: {self.detail}"
        return f"{self.title}: {self.detail}"

    def __repr__(self):
        return f"kdrt.Error(kind={self.kind!r}, status={self.status}, title={self.title!r}, " \
               f"detail={self.detail!r})"

    @classmethod
    def from_response(cls, status: int, content_type: str, body: bytes, request_id: str = ""):
        """The Error of a non-2xx answer: a problem+json body fills the fields; any other body
        becomes the detail (its first 300 bytes) with the HTTP reason phrase as title."""
        problem = None
        text = body.decode("utf-8", "replace")
        if "problem+json" in content_type or text.lstrip().startswith("{"):
            try:
                decoded = json.loads(text)
                if isinstance(decoded, dict) and "detail" in decoded:
                    problem = decoded
            except ValueError:
                problem = None
        if problem is not None:
            return cls(
                kind="server", status=status,
                title=str(problem.get("title", "")),
                detail=str(problem.get("detail", "")),
                type=str(problem.get("type", "")),
                code=str(problem.get("code", "")),
                request_id=str(problem.get("request_id", "") or request_id),
                line=problem.get("line"),
                byte_offset=problem.get("byte_offset"),
                limit=problem.get("limit"),
                retry_after=problem.get("retry_after"),
                problem=problem,
            )
        try:
            reason = HTTPStatus(status).phrase
        except ValueError:
            reason = f"HTTP {status}"
        detail = "".join(c if c.isprintable() else " " for c in text[:300])
        return cls(kind="server", status=status, title=reason, detail=detail,
                   request_id=request_id)
