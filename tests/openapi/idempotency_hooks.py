"""schemathesis hooks of tests/openapi_contract.rs (loaded through SCHEMATHESIS_HOOKS).

A client sends a fresh Idempotency-Key with every new request and the same key only with a
retry of that request (api/README.md). schemathesis draws short keys ("0") and sends them
with different requests, which the API rightly refuses (422, key reused): each call gets a key
of its own instead. Negative cases keep theirs: editing a case revalidates it, and a case
that lacks its Authorization header on purpose would be sent with it again. Replays of a key are tested by api/tests/feed.rs and
tests/idempotent_restarts.rs.
"""
import uuid

import schemathesis


@schemathesis.hook
def before_call(context, case, kwargs):
    negative = case.meta is not None and case.meta.generation.mode.is_negative
    if not negative and case.headers and "Idempotency-Key" in case.headers:
        case.headers["Idempotency-Key"] = uuid.uuid4().hex
