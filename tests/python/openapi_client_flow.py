"""A client generated from the committed OpenAPI document parses every response of the end-to-end
API flow. Driven by tests/openapi_contract.rs:

    python3 openapi_client_flow.py OPENAPI_JSON BASE_URL ADMIN_TOKEN WORKDIR

datamodel-code-generator (PyPI) turns the document's schemas into pydantic models; each response
is validated against the model its operation's document names, with undocumented fields refused
(extra="forbid"), so a response that drifted from the document fails here.
"""

import importlib.util
import json
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pydantic

doc_path, base, token, work = sys.argv[1], sys.argv[2].rstrip("/"), sys.argv[3], Path(sys.argv[4])
doc = json.loads(Path(doc_path).read_text())
models_py = work / "ufops_models.py"
subprocess.run(
    ["datamodel-codegen", "--input", doc_path, "--input-file-type", "openapi", "--output", str(models_py),
     "--output-model-type", "pydantic_v2.BaseModel", "--disable-timestamp"],
    check=True,
)
spec = importlib.util.spec_from_file_location("ufops_models", models_py)
models = importlib.util.module_from_spec(spec)
sys.modules["ufops_models"] = models
spec.loader.exec_module(models)
for obj in list(vars(models).values()):
    if isinstance(obj, type) and issubclass(obj, pydantic.BaseModel) and obj is not pydantic.BaseModel \
            and obj.__name__ != "Problem" and "root" not in obj.model_fields:
        obj.model_config["extra"] = "forbid"
        obj.model_rebuild(force=True, _types_namespace=vars(models))


def py_type(schema):
    """The Python type of a response schema of the document."""
    if "$ref" in schema:
        return getattr(models, schema["$ref"].rsplit("/", 1)[1])
    t = schema.get("type")
    if t == "array":
        return list[py_type(schema["items"])]
    return {"string": str, "integer": int, "number": float, "boolean": bool}.get(t, object)


def find_operation(method, path):
    """The document's operation for a concrete path (`/v1/jobs/abc` matches `/v1/jobs/{id}`)."""
    parts = path.split("?")[0].strip("/").split("/")
    for templ, item in doc["paths"].items():
        tp = templ.strip("/").split("/")
        if len(tp) == len(parts) and all(a.startswith("{") or a == b for a, b in zip(tp, parts)):
            if method.lower() in item:
                return templ, item[method.lower()]
    raise AssertionError(f"{method} {path}: no operation in the document")


parsed = []


def call(method, path, body=None, headers=None, want=None):
    h = {"Authorization": f"Bearer {token}", **(headers or {})}
    data = None
    if body is not None:
        data = json.dumps(body).encode()
        h["Content-Type"] = "application/json"
    req = urllib.request.Request(base + path, data=data, method=method, headers=h)
    try:
        with urllib.request.urlopen(req) as r:
            status, ctype, raw, rh = r.status, r.headers.get("Content-Type", ""), r.read(), r.headers
    except urllib.error.HTTPError as e:
        status, ctype, raw, rh = e.code, e.headers.get("Content-Type", ""), e.read(), e.headers
    if want is not None:
        assert status == want, f"{method} {path}: {status} {raw[:300]!r}"
    templ, op = find_operation(method, path)
    resp = op["responses"].get(str(status))
    assert resp is not None, f"{method} {templ}: status {status} is not documented"
    ctype = ctype.split(";")[0].strip()
    content = resp.get("content", {})
    if status == 204:
        assert not raw
        parsed.append(f"{method} {templ} {status}")
        return None, rh
    assert ctype in content or "*/*" in content, f"{method} {templ} {status}: {ctype} not among {list(content)}"
    if ctype not in content or ctype not in ("application/json", "application/problem+json"):
        # A file download (`*/*`): its bytes are the artifact's or export's, not a record.
        parsed.append(f"{method} {templ} {status} ({ctype})")
        return raw, rh
    value = json.loads(raw)
    typ = py_type(content[ctype]["schema"])
    if typ is not object:
        pydantic.TypeAdapter(typ).validate_python(value)
        parsed.append(f"{method} {templ} {status}")
    return value, rh


call("GET", "/healthz", want=200)
call("GET", "/v1/policies", want=200)
call("GET", "/v1/checkpoints?policy=bc", want=200)
call("GET", "/v1/tasks", want=200)
versions, _ = call("GET", "/v1/versions", want=200)
head = versions[-1]["version"]
call("GET", f"/v1/versions/{head}", want=200)
page, _ = call("GET", "/v1/episodes?policy=bc&limit=5", want=200)
assert page["next_cursor"]
call("GET", f"/v1/episodes?after={page['next_cursor']}&limit=5&sort=id", want=200)
call("GET", "/v1/episodes/counts?policy=bc", want=200)
ep_id = page["episodes"][0]["id"]
_, h = call("GET", f"/v1/episodes/{ep_id}", want=200)
call("GET", f"/v1/episodes/{ep_id}/steps", want=200)
call("GET", f"/v1/episodes/{ep_id}/steps", headers={"Accept": "application/vnd.apache.arrow.stream"}, want=200)
call("PUT", f"/v1/episodes/{ep_id}/label", {"label": "failure", "note": "contract"}, {"If-Match": h["ETag"]}, want=200)
call("PUT", f"/v1/episodes/{ep_id}/label", {"label": "success"}, {"If-Match": h["ETag"]}, want=409)
call("PUT", f"/v1/episodes/{ep_id}/label", {"label": "success"}, want=428)
other = page["episodes"][1]["id"]
call("POST", "/v1/labels/bulk", {"updates": [{"episode_id": other, "label": "unknown"}]}, want=200)
snap, _ = call("POST", "/v1/label-snapshots", {"message": "contract"}, want=201)
call("POST", "/v1/label-snapshots", {}, want=200)
call("GET", f"/v1/versions/{head}/diff/{snap['version']}", want=200)
split, _ = call("POST", "/v1/splits", {"policy": "bc", "checkpoint": "e600", "seed": 3}, want=201)
call("GET", "/v1/splits", want=200)
call("GET", f"/v1/splits/{split['id']}", want=200)
job, _ = call("POST", "/v1/jobs", {"split_id": split["id"], "kind": "classifier", "chunk_len": 16, "config": {"epochs": 1}}, want=201)
call("GET", "/v1/jobs?state=queued", want=200)
call("GET", f"/v1/jobs/{job['id']}", want=200)
call("POST", f"/v1/jobs/{job['id']}/cancel", want=200)
arts, _ = call("GET", "/v1/artifacts?policy=bc", want=200)
art = arts[0]
call("GET", f"/v1/artifacts/{art['id']}", want=200)
call("GET", f"/v1/artifacts/{art['id']}/files/{art['files'][0]['name']}", want=200)
call("PUT", f"/v1/artifacts/{art['id']}/aliases/contract", want=200)
call("GET", "/v1/policies/bc/checkpoints/e600/verifiers/classifier@contract", want=200)
call("GET", f"/v1/policies/bc/checkpoints/e600/verifiers/classifier@contract/files/{art['files'][0]['name']}", want=200)
call("GET", "/v1/policies/bc/checkpoints/e600/verifiers/classifier@nope", want=404)
export, _ = call("POST", "/v1/exports", {"format": "lerobot", "policy": "bc"}, want=201)
curated = {"format": "robomimic", "policy": "bc", "score": {"artifact": "bc/e600/classifier@contract", "min": 0.5}}
call("POST", "/v1/exports", curated, want=201)
call("GET", "/v1/exports", want=200)
call("GET", f"/v1/exports/{export['id']}", want=200)
call("DELETE", f"/v1/exports/{export['id']}", want=409)
call("GET", "/v1/scoreboard?policy=bc", want=200)
call("GET", "/v1/scoreboard?policy=bc&format=csv", want=200)
call("GET", "/v1/runs", want=200)
created, _ = call("POST", "/v1/tokens", {"name": "contract-viewer", "role": "viewer"}, want=201)
call("GET", "/v1/tokens", want=200)
call("DELETE", f"/v1/tokens/{created['record']['id']}", want=204)
call("POST", "/v1/gc", {"dry_run": True}, want=200)
call("GET", "/v1/jobs/no-such-job", want=404)
call("GET", "/v1/episodes?sort=label", want=400)
print(json.dumps({"parsed": parsed}))
