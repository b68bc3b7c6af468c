"""Login, tokens, roles and user management through a real server."""

from __future__ import annotations

import httpx

from tests.api.server import ADMIN_PASSWORD, Server


def test_first_start_creates_admin_from_the_environment(server: Server) -> None:
    with server.client() as admin:
        me = admin.get("/auth/me").json()
    assert me["username"] == "admin" and me["role"] == "admin"


def test_wrong_password_and_missing_token_are_401(server: Server) -> None:
    response = httpx.post(f"{server.url}/auth/login", json={"username": "admin", "password": "x"})
    assert response.status_code == 401
    assert response.json()["detail"] == "wrong username or password"
    assert httpx.get(f"{server.url}/auth/me").status_code == 401
    forged = {"Authorization": "Bearer eyJ1IjoxLCJ2IjoxLCJlIjo5OTk5OTk5OTk5fQ.forged"}
    assert httpx.get(f"{server.url}/auth/me", headers=forged).status_code == 401


def test_admin_creates_users_and_roles_are_enforced(server: Server) -> None:
    annotator = server.add_user("anna", "annotator")
    assert annotator.get("/auth/me").json()["role"] == "annotator"
    refused = annotator.post(
        "/users", json={"username": "eve", "password": "password-123", "role": "admin"}
    )
    assert refused.status_code == 403
    assert "annotator" in refused.json()["detail"]
    with server.client() as admin:
        duplicate = admin.post(
            "/users", json={"username": "anna", "password": "password-123", "role": "reviewer"}
        )
        assert duplicate.status_code == 409
        short = admin.post("/users", json={"username": "bob", "password": "short"})
        assert short.status_code == 422
        assert short.json()["detail"].startswith("password:")
        bad_role = admin.post(
            "/users", json={"username": "bob", "password": "password-123", "role": "boss"}
        )
        assert bad_role.status_code == 422 and bad_role.json()["detail"].startswith("role:")
        assert admin.patch("/users/999", json={"role": "reviewer"}).status_code == 404
        anna_id = annotator.get("/auth/me").json()["id"]
        promoted = admin.patch(f"/users/{anna_id}", json={"role": "reviewer"})
        assert promoted.status_code == 200 and promoted.json()["role"] == "reviewer"
    # the role change invalidated the old token
    assert annotator.get("/auth/me").status_code == 401
    annotator.close()


def test_the_last_active_admin_stays_an_admin(server: Server) -> None:
    with server.client() as admin:
        me = admin.get("/auth/me").json()["id"]
        for change in ({"role": "reviewer"}, {"is_active": False}):
            refused = admin.patch(f"/users/{me}", json=change)
            assert refused.status_code == 409
            assert refused.json()["detail"] == (
                "user 'admin' is the last active admin; make another user admin first"
            )
        assert admin.get("/auth/me").json()["role"] == "admin"  # nothing changed, still logged in
        second = admin.post(
            "/users", json={"username": "root2", "password": "password-123", "role": "admin"}
        ).json()["id"]
        # with another admin either may go; then the other is the last one
        assert admin.patch(f"/users/{second}", json={"is_active": False}).status_code == 200
        assert admin.patch(f"/users/{me}", json={"role": "reviewer"}).status_code == 409
        assert admin.patch(f"/users/{second}", json={"is_active": True}).status_code == 200
        assert admin.patch(f"/users/{second}", json={"role": "annotator"}).status_code == 200
        assert admin.patch(f"/users/{second}", json={"password": "password-456"}).status_code == 200


def test_cookie_is_accepted_for_reads_only(server: Server) -> None:
    client = httpx.Client(base_url=server.url)
    client.post("/auth/login", json={"username": "admin", "password": ADMIN_PASSWORD})
    assert client.get("/auth/me").status_code == 200  # cookie read
    write = client.post(
        "/users", json={"username": "cookie", "password": "password-123", "role": "annotator"}
    )
    assert write.status_code == 401  # a write needs the bearer token
    client.close()
