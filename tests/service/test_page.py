"""The web page's serving (``service/page.py``), without a browser: GET / and /static need no API key,
stay out of the OpenAPI schema, every module the page imports resolves to a file the service serves,
nothing is loaded from outside, and the files ship in the wheel. tests/test_page_browser.py runs it."""

from __future__ import annotations

import json
import re
import tomllib

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.page import STATIC
from tests.helpers import ROOT
from worker.settings import Settings

OWN_FILES = sorted([STATIC / "index.html", STATIC / "page.css", *(STATIC / "js").glob("*.js")])


@pytest.fixture(scope="module")
def client():
    # No `with`: the lifespan (which connects to Redis) does not run; these routes never use it.
    return TestClient(create_app(Settings(redis_url="redis://127.0.0.1:1/0", api_key="the-key")))


def _import_map() -> dict[str, str]:
    html = (STATIC / "index.html").read_text()
    return json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]


def test_page_and_its_files_need_no_api_key(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert '<script type="importmap">' in page.text
    assert client.get("/static/js/main.js").headers["content-type"].startswith("text/javascript")
    assert client.get("/static/page.css").headers["content-type"].startswith("text/css")
    assert client.get("/static/vendor/three/three.module.js").status_code == 200
    assert client.get("/openapi.json").status_code == 200  # the page builds its form from it
    assert client.get("/static/no-such-file.js").status_code == 404
    assert client.get("/v1/jobs/" + "a" * 22).status_code == 401  # /v1 still needs the key


def test_page_routes_are_not_in_the_openapi_schema(client):
    paths = client.get("/openapi.json").json()["paths"]
    assert "/" not in paths and not any(path.startswith("/static") for path in paths)


def test_every_import_of_the_page_resolves_to_a_served_file(client):
    imports = _import_map()
    for target in imports.values():
        assert client.get("/" + target.removeprefix("./")).status_code == 200 or target.endswith("/"), target
    pattern = re.compile(r"""(?:\bfrom\s*|\bimport\s*\(?\s*)['"]([^'"]+)['"]""")
    modules = [*(STATIC / "js").glob("*.js"), *(STATIC / "vendor" / "three").rglob("*.js")]
    for module in modules:
        for specifier in pattern.findall(module.read_text()):
            if specifier.startswith("."):
                assert (module.parent / specifier).resolve().is_file(), f"{module.name} imports {specifier}"
            else:
                mapped = [key for key in imports if specifier == key or (key[-1] == "/" and specifier.startswith(key))]
                assert mapped, f"{module.name} imports {specifier}, which the import map does not map"
                prefix = max(mapped, key=len)
                path = imports[prefix] + specifier.removeprefix(prefix)
                assert client.get("/" + path.removeprefix("./")).status_code == 200, f"{specifier} -> {path}"


def test_the_page_loads_nothing_from_outside():
    for path in OWN_FILES:
        text = path.read_text()
        assert not re.search(r"""(?:src|href|import|from|url)\s*[=(]?\s*['"]?(?:https?:)?//""", text), path


def test_the_static_files_ship_in_the_wheel():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["service"]
    packaged = {path for pattern in patterns for path in (ROOT / "service").glob(pattern) if path.is_file()}
    assert {path for path in STATIC.rglob("*") if path.is_file()} <= packaged
    assert (STATIC / "vendor" / "three" / "LICENSE").is_file()
