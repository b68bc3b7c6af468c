"""Passwords and login tokens.

Passwords are hashed with scrypt (stdlib `hashlib.scrypt`, a memory-hard password hash) and a
random salt per user; the stored string names its parameters so they can be raised later
without breaking old hashes.

A login token is `<payload>.<signature>`: the payload (user id, the user's record version at
login, the login session's id, expiry) in URL-safe base64, signed with HMAC-SHA256 under a
secret kept in the data directory (`secret.key`, created once, readable by its owner only).
The signature is checked first, so a forged or altered token is refused without a database
look-up; then the session it names must still be live (`app.store.sessions`): logout,
revocation and any change to the user (password, role, deactivation) end it.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path

SCRYPT_N = 2**14
SCRYPT_R = 8
SCRYPT_P = 1
TOKEN_LIFETIME_S = 12 * 3600


def hash_password(password: str) -> str:
    salt = secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P)
    return "$".join(
        ("scrypt", str(SCRYPT_N), str(SCRYPT_R), str(SCRYPT_P), _b64(salt), _b64(digest))
    )


def verify_password(password: str, stored: str) -> bool:
    """True when `password` matches the stored hash; False for any malformed hash."""
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != "scrypt":
            return False
        expected = _unb64(digest)
        actual = hashlib.scrypt(
            password.encode(), salt=_unb64(salt), n=int(n), r=int(r), p=int(p), dklen=len(expected)
        )
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(actual, expected)


@dataclass(frozen=True)
class TokenClaims:
    user_id: int
    user_version: int
    session_id: int
    expires_at: float


class TokenSigner:
    """Issues and checks login tokens with one secret key."""

    def __init__(self, key: bytes):
        self._key = key

    @classmethod
    def for_data_dir(cls, data_dir: Path) -> TokenSigner:
        return cls(load_or_create_secret(Path(data_dir) / "secret.key"))

    def issue(
        self,
        user_id: int,
        user_version: int,
        session_id: int,
        lifetime_s: float = TOKEN_LIFETIME_S,
    ) -> str:
        claims = {
            "u": int(user_id),
            "v": int(user_version),
            "s": int(session_id),
            "e": round(time.time() + lifetime_s),
        }
        payload = _b64(json.dumps(claims, separators=(",", ":")).encode())
        return f"{payload}.{self._sign(payload)}"

    def check(self, token: str) -> TokenClaims | None:
        """The claims of a validly signed, unexpired token (None otherwise); whether its session
        is still live is the store's to say."""
        payload, _, signature = token.partition(".")
        if not payload or not hmac.compare_digest(signature, self._sign(payload)):
            return None
        try:
            claims = json.loads(_unb64(payload))
            result = TokenClaims(
                int(claims["u"]), int(claims["v"]), int(claims["s"]), float(claims["e"])
            )
        except (ValueError, KeyError, TypeError):
            return None
        return result if result.expires_at > time.time() else None

    def _sign(self, payload: str) -> str:
        return _b64(hmac.new(self._key, payload.encode(), hashlib.sha256).digest())


def load_or_create_secret(path: Path) -> bytes:
    """The secret in `path`, created (32 random bytes, mode 0600) when missing.

    Creation is atomic (`O_EXCL`), so two processes starting at once agree on one key.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        for _ in range(100):  # the creator may still be writing
            key = path.read_bytes()
            if len(key) >= 32:
                return key
            time.sleep(0.01)
        raise
    key = secrets.token_bytes(32)
    with os.fdopen(fd, "wb") as f:
        f.write(key)
    return key


def _b64(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
