"""Accounts, sessions and API tokens in SQLite (<data dir>/accounts.sqlite3).

Roles: educator (everything), student (own projects/runs, drives while holding the bench lease),
observer (read-only). Passwords are hashed with argon2id (19 MiB, 2 passes, 1 lane:
OWASP's minimum profile, light enough for a login rush on a Pi). Session and API tokens are 256-bit random strings; only their SHA-256 is stored (they
are not guessable, so a fast hash is enough and a stolen database holds no usable token).

Used synchronously from the event loop like server/runs/store.py (a few sub-millisecond statements per
request); password hashing is the slow part and the callers run it in a thread.
"""

from __future__ import annotations

import builtins  # `Accounts.list` shadows the builtin inside the class body
import csv
import hashlib
import hmac
import io
import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

from ...errors import XrfError
from ...private_files import private_db
from .roles import ROLES, USERNAME_RE, Perm, role_has

MIN_PASSWORD = 10
MAX_PASSWORD = 256

_SCHEMA = """
CREATE TABLE IF NOT EXISTS users (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    username TEXT NOT NULL UNIQUE,
    full_name TEXT NOT NULL DEFAULT '',
    email TEXT NOT NULL DEFAULT '',
    role TEXT NOT NULL,
    password_hash TEXT NOT NULL,
    disabled INTEGER NOT NULL DEFAULT 0,
    must_change INTEGER NOT NULL DEFAULT 1,   -- a one-time password: change it at first login
    created REAL NOT NULL,
    last_login REAL
);
CREATE TABLE IF NOT EXISTS sessions (
    token_hash TEXT PRIMARY KEY,
    user_id INTEGER NOT NULL,
    csrf TEXT NOT NULL,
    created REAL NOT NULL,
    last_seen REAL NOT NULL,
    expires REAL NOT NULL,
    address TEXT NOT NULL DEFAULT ''
);
CREATE TABLE IF NOT EXISTS keys (              -- server-side secrets, e.g. the device-cookie key
    name TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS api_tokens (
    token_hash TEXT PRIMARY KEY,
    user_id INTEGER NOT NULL UNIQUE,          -- one token per user; a new login replaces it
    created REAL NOT NULL,
    last_used REAL
);
"""

# argon2id with OWASP's minimum profile (19 MiB, 2 passes, 1 lane): memory-hard, yet 40 students
# logging in at the start of a lab do not exhaust a Pi's memory (callers also bound concurrency).
_hasher = PasswordHasher(time_cost=2, memory_cost=19 * 1024, parallelism=1)
# Verified against when the username does not exist, so a wrong username costs as much time as a
# wrong password and timing does not tell which accounts exist.
_DUMMY_HASH = _hasher.hash(secrets.token_urlsafe(16))


class AccountError(XrfError):
    """An account request refused (422 by default; 409 a taken name, 404 no such user): an
    XrfError, so the routes let server/http/errors.py answer it."""

    status = 422


@dataclass(frozen=True)
class User:
    id: int
    username: str
    role: str
    full_name: str = ""
    email: str = ""
    disabled: bool = False
    must_change: bool = False
    created: float = 0.0
    last_login: float | None = None

    @property
    def is_educator(self) -> bool:
        """Has the educator's powers (roles.py): drives without the lease, sees everyone's."""
        return role_has(self.role, Perm.EDUCATOR)

    def public(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "username": self.username,
            "role": self.role,
            "full_name": self.full_name,
            "email": self.email,
            "disabled": self.disabled,
            "must_change": self.must_change,
            "created": self.created,
            "last_login": self.last_login,
        }


@dataclass(frozen=True)
class Session:
    token_hash: str
    user: User
    csrf: str
    expires: float


_USER_COLUMNS = "id, username, role, full_name, email, disabled, must_change, created, last_login"


def _user(r: tuple[Any, ...]) -> User:
    return User(
        id=r[0],
        username=r[1],
        role=r[2],
        full_name=r[3],
        email=r[4],
        disabled=bool(r[5]),
        must_change=bool(r[6]),
        created=r[7],
        last_login=r[8],
    )


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def new_secret() -> str:
    """A one-time password: 16 characters from an unambiguous alphabet (~80 bits)."""
    alphabet = "abcdefghjkmnpqrstuvwxyzACDEFGHJKLMNPQRTUVWXY34679"
    return "".join(secrets.choice(alphabet) for _ in range(16))


def check_password_rules(password: str, username: str = "") -> None:
    if not isinstance(password, str) or len(password) < MIN_PASSWORD:
        raise AccountError(f"a password has at least {MIN_PASSWORD} characters")
    if len(password) > MAX_PASSWORD:
        raise AccountError(f"a password has at most {MAX_PASSWORD} characters")
    if username and password.lower() == username.lower():
        raise AccountError("the password must not be the username")


def check_username(username: str) -> str:
    username = (username or "").strip().lower()
    if not USERNAME_RE.match(username):
        raise AccountError(
            f"username {username!r}: 2-32 characters a-z, 0-9, '.', '_', '-', starting with a letter or digit"
        )
    return username


def check_role(role: str) -> str:
    role = (role or "").strip().lower()
    if role not in ROLES:
        raise AccountError(f"role {role!r}: one of {', '.join(ROLES)}")
    return role


class Accounts:
    def __init__(self, path: Path, session_max_s: float = 12 * 3600, session_idle_s: float = 2 * 3600) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        private_db(path)  # 0600 before SQLite opens it: its WAL/SHM take the same mode
        self._db = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)
        self._lock = threading.Lock()  # password checks run in threads; writes are serialised
        self.session_max_s = session_max_s
        self.session_idle_s = session_idle_s

    def close(self) -> None:
        self._db.close()

    # -- users ------------------------------------------------------------------------------------

    def count(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM users").fetchone()[0])

    def get(self, user_id: int) -> User | None:
        if not -(2**63) <= user_id < 2**63:
            return None
        r = self._db.execute(f"SELECT {_USER_COLUMNS} FROM users WHERE id=?", (user_id,)).fetchone()
        return _user(r) if r else None

    def by_name(self, username: str) -> User | None:
        r = self._db.execute(
            f"SELECT {_USER_COLUMNS} FROM users WHERE username=?", ((username or "").strip().lower(),)
        ).fetchone()
        return _user(r) if r else None

    def list(self) -> list[User]:
        return [_user(r) for r in self._db.execute(f"SELECT {_USER_COLUMNS} FROM users ORDER BY role, username")]

    def create(
        self,
        username: str,
        role: str,
        password: str | None = None,
        full_name: str = "",
        email: str = "",
        must_change: bool = True,
    ) -> tuple[User, str]:
        """A new account; returns it and its password (generated when not given: a one-time one)."""
        username = check_username(username)
        role = check_role(role)
        full_name, email = _text(full_name, "full name", 200), _text(email, "email", 200)
        if password is None:
            password = new_secret()
            must_change = True
        else:
            check_password_rules(password, username)
        pw_hash = _hasher.hash(password)
        with self._lock:
            if self.by_name(username) is not None:
                raise AccountError(f"username {username!r} is taken", 409)
            cur = self._db.execute(
                "INSERT INTO users (username, full_name, email, role, password_hash, must_change, created) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (username, full_name, email, role, pw_hash, int(must_change), time.time()),
            )
        user = self.get(int(cur.lastrowid or 0))
        assert user is not None
        return user, password

    def parse_class_list(self, text: str) -> builtins.list[dict[str, str]]:
        """CSV `username,full name,role[,email]` (a header row is allowed). Every row is checked
        before anything is created: one bad row refuses the whole list, naming each problem."""
        rows: list[dict[str, str]] = []
        errors: list[str] = []
        seen: set[str] = set()
        try:  # a lone carriage return inside a field is a csv.Error: a bad list, not a crash
            table = list(csv.reader(io.StringIO(text.lstrip("\ufeff"))))
        except csv.Error as exc:
            raise AccountError(f"the class list is not valid CSV ({exc})") from None
        for n, cells in enumerate(table, 1):
            cells = [c.strip() for c in cells]
            if not any(cells) or cells[0].startswith("#"):
                continue
            if n == 1 and cells[0].lower() == "username":
                continue
            if len(cells) not in (3, 4):
                errors.append(f"line {n}: expected username,full name,role[,email], got {len(cells)} fields")
                continue
            try:
                username = check_username(cells[0])
                role = check_role(cells[2])
                full_name = _text(cells[1], "full name", 200)
                email = _text(cells[3] if len(cells) == 4 else "", "email", 200)
            except AccountError as exc:
                errors.append(f"line {n}: {exc}")
                continue
            if username in seen:
                errors.append(f"line {n}: {username} appears twice")
            elif self.by_name(username) is not None:
                errors.append(f"line {n}: {username} already has an account")
            seen.add(username)
            rows.append({"username": username, "full_name": full_name, "role": role, "email": email})
        if errors:
            raise AccountError("; ".join(errors[:50]))
        if not rows:
            raise AccountError("the class list has no accounts")
        return rows

    def update(self, user_id: int, **values: Any) -> User:
        allowed = {"role", "full_name", "email", "disabled"}
        values = {k: v for k, v in values.items() if v is not None}
        if set(values) - allowed:
            raise AccountError(f"cannot change {sorted(set(values) - allowed)}")
        if "role" in values:
            values["role"] = check_role(values["role"])
        for k in ("full_name", "email"):
            if k in values:
                values[k] = _text(values[k], k, 200)
        if "disabled" in values:
            values["disabled"] = int(bool(values["disabled"]))
        with self._lock:
            if self.get(user_id) is None:
                raise AccountError(f"no user {user_id}", 404)
            if values:
                self._db.execute(
                    f"UPDATE users SET {', '.join(k + '=?' for k in values)} WHERE id=?", (*values.values(), user_id)
                )
            if values.get("disabled") or "role" in values:
                self.revoke(user_id)
        user = self.get(user_id)
        assert user is not None
        return user

    def set_password(self, user_id: int, password: str | None = None, must_change: bool = False) -> str:
        """A new password (generated and one-time when None); every session and token ends."""
        user = self.get(user_id)
        if user is None:
            raise AccountError(f"no user {user_id}", 404)
        if password is None:
            password, must_change = new_secret(), True
        else:
            check_password_rules(password, user.username)
        pw_hash = _hasher.hash(password)
        with self._lock:
            self._db.execute(
                "UPDATE users SET password_hash=?, must_change=? WHERE id=?", (pw_hash, int(must_change), user_id)
            )
            self.revoke(user_id)
        return password

    def verify(self, username: str, password: str) -> User | None:
        """The user when the password is right and the account enabled; None otherwise. Slow
        (argon2): call it from a thread."""
        r = self._db.execute(
            "SELECT id, password_hash FROM users WHERE username=?", ((username or "").strip().lower(),)
        ).fetchone()
        stored = r[1] if r else _DUMMY_HASH
        try:
            _hasher.verify(stored, password or "")
            ok = r is not None
        except (VerifyMismatchError, VerificationError, InvalidHashError):
            ok = False
        if not ok:
            return None
        user = self.get(r[0])
        if user is None or user.disabled:
            return None
        if _hasher.check_needs_rehash(stored):
            with self._lock:
                self._db.execute("UPDATE users SET password_hash=? WHERE id=?", (_hasher.hash(password), user.id))
        return user

    # -- the lab room's class list (room/accounts_sync.py) ----------------------------------------

    def export_hashed(self) -> builtins.list[dict[str, Any]]:
        """Every account with its password hash: what the room sends its enrolled benches (argon2id
        hashes only; a bench checks a password exactly as the room would)."""
        rows = self._db.execute(
            "SELECT username, role, full_name, email, password_hash, disabled, must_change FROM users ORDER BY username"
        ).fetchall()
        return [
            {
                "username": r[0],
                "role": r[1],
                "full_name": r[2],
                "email": r[3],
                "password_hash": r[4],
                "disabled": bool(r[5]),
                "must_change": bool(r[6]),
            }
            for r in rows
        ]

    def put_hashed(
        self,
        username: str,
        role: str,
        password_hash: str,
        full_name: str = "",
        email: str = "",
        disabled: bool = False,
        must_change: bool = False,
    ) -> tuple[User, bool]:
        """Create or update an account from a hash made elsewhere (the room). Returns the user and
        whether its sessions and token were ended (new password, disabled, other role)."""
        username, role = check_username(username), check_role(role)
        if not password_hash.startswith("$argon2"):
            raise AccountError(f"{username}: not an argon2 hash")
        full_name, email = _text(full_name, "full name", 200), _text(email, "email", 200)
        with self._lock:
            r = self._db.execute(
                "SELECT id, role, password_hash, disabled FROM users WHERE username=?", (username,)
            ).fetchone()
            if r is None:
                self._db.execute(
                    "INSERT INTO users (username, full_name, email, role, password_hash, disabled, "
                    "must_change, created) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (username, full_name, email, role, password_hash, int(disabled), int(must_change), time.time()),
                )
                revoked = False
            else:
                revoked = r[1] != role or r[2] != password_hash or (bool(disabled) and not r[3])
                self._db.execute(
                    "UPDATE users SET full_name=?, email=?, role=?, password_hash=?, disabled=?, "
                    "must_change=? WHERE id=?",
                    (full_name, email, role, password_hash, int(disabled), int(must_change), r[0]),
                )
                if revoked:
                    self.revoke(r[0])
        user = self.by_name(username)
        assert user is not None
        return user, revoked

    def educators_enabled(self) -> int:
        """Enabled accounts with the educator's powers (whichever roles roles.py gives them)."""
        powers = [r for r in ROLES if role_has(r, Perm.EDUCATOR)]
        marks = ",".join("?" * len(powers))
        row = self._db.execute(f"SELECT COUNT(*) FROM users WHERE role IN ({marks}) AND disabled=0", powers).fetchone()
        return int(row[0])

    # -- sessions ---------------------------------------------------------------------------------

    def new_session(self, user: User, address: str = "") -> tuple[str, str]:
        """A session for `user`: returns (token for the cookie, CSRF token)."""
        token, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        now = time.time()
        with self._lock:
            self._db.execute(
                "INSERT INTO sessions (token_hash, user_id, csrf, created, last_seen, expires, address) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (token_hash(token), user.id, csrf, now, now, now + self.session_max_s, address[:100]),
            )
            self._db.execute("UPDATE users SET last_login=? WHERE id=?", (now, user.id))
            self._db.execute(
                "DELETE FROM sessions WHERE expires < ? OR last_seen < ?", (now, now - self.session_idle_s)
            )
        return token, csrf

    def session(self, token: str) -> Session | None:
        """The live session of a cookie value; None when unknown, expired, idle too long or the
        account is disabled. Touching it extends the idle timeout (written at most every 30 s)."""
        if not token or len(token) > 200:
            return None
        h = token_hash(token)
        r = self._db.execute(
            "SELECT user_id, csrf, last_seen, expires FROM sessions WHERE token_hash=?", (h,)
        ).fetchone()
        if r is None:
            return None
        user_id, csrf, last_seen, expires = r
        now = time.time()
        if now >= expires or now - last_seen >= self.session_idle_s:
            self._db.execute("DELETE FROM sessions WHERE token_hash=?", (h,))
            return None
        user = self.get(user_id)
        if user is None or user.disabled:
            return None
        if now - last_seen > min(30.0, self.session_idle_s / 4):
            self._db.execute("UPDATE sessions SET last_seen=? WHERE token_hash=?", (now, h))
        return Session(h, user, csrf, expires)

    def end_session(self, token_hash_: str) -> None:
        self._db.execute("DELETE FROM sessions WHERE token_hash=?", (token_hash_,))

    def revoke(self, user_id: int, keep: str | None = None) -> None:
        """End every session (but `keep`, a token hash) and the API token of a user."""
        self._db.execute("DELETE FROM sessions WHERE user_id=? AND token_hash IS NOT ?", (user_id, keep))
        self._db.execute("DELETE FROM api_tokens WHERE user_id=?", (user_id,))

    # -- API tokens (the CLI) ---------------------------------------------------------------------

    def new_api_token(self, user: User) -> str:
        token = "xrf_" + secrets.token_urlsafe(32)
        with self._lock:
            self._db.execute("DELETE FROM api_tokens WHERE user_id=?", (user.id,))
            self._db.execute(
                "INSERT INTO api_tokens (token_hash, user_id, created) VALUES (?, ?, ?)",
                (token_hash(token), user.id, time.time()),
            )
        return token

    def api_token_user(self, token: str) -> User | None:
        if not token or len(token) > 200:
            return None
        h = token_hash(token)
        r = self._db.execute("SELECT user_id, last_used FROM api_tokens WHERE token_hash=?", (h,)).fetchone()
        if r is None:
            return None
        user = self.get(r[0])
        if user is None or user.disabled:
            return None
        now = time.time()
        if r[1] is None or now - r[1] > 60:
            self._db.execute("UPDATE api_tokens SET last_used=? WHERE token_hash=?", (now, h))
        return user

    def drop_api_token(self, user_id: int) -> None:
        self._db.execute("DELETE FROM api_tokens WHERE user_id=?", (user_id,))

    # -- device cookies (LoginGuard) --------------------------------------------------------------

    def _device_key(self) -> bytes:
        return self._key("device")

    def _key(self, name: str) -> bytes:
        """A secret of this appliance, made on first use and kept in the accounts database."""
        with self._lock:
            r = self._db.execute("SELECT value FROM keys WHERE name=?", (name,)).fetchone()
            if r is None:
                value = secrets.token_hex(32)
                self._db.execute("INSERT INTO keys (name, value) VALUES (?, ?)", (name, value))
                return bytes.fromhex(value)
        return bytes.fromhex(r[0])

    # -- links: one resource for one user, for a client that sends no cookie ----------------------
    # rerun's web viewer fetches a recording's URL without the session cookie (a 401 left it
    # empty), so the page hands it a link that is its own credential: the user, an expiry and a
    # MAC over them and the one resource (`scope`, e.g. a run's log), with a key of this appliance.
    # Nothing is stored; a disabled account's links stop working with it.

    def new_link(self, user: User, scope: str, ttl_s: float) -> str:
        expires = int(time.time() + ttl_s)
        return f"{user.id}.{expires}.{self._link_mac(user.id, expires, scope)}"

    def link_user(self, link: str, scope: str) -> User | None:
        """The user of `link` when it was made for `scope` and has not expired, else None."""
        parts = link.split(".") if len(link) <= 100 else []
        if len(parts) != 3 or not parts[0].isdigit() or not parts[1].isdigit():
            return None
        user_id, expires = int(parts[0]), int(parts[1])
        if expires < time.time() or not hmac.compare_digest(parts[2], self._link_mac(user_id, expires, scope)):
            return None
        user = self.get(user_id)
        return user if user is not None and not user.disabled else None

    def _link_mac(self, user_id: int, expires: int, scope: str) -> str:
        return hmac.new(self._key("link"), f"{user_id}|{expires}|{scope}".encode(), hashlib.sha256).hexdigest()[:40]

    def _device_mac(self, username: str, nonce: str) -> str:
        return hmac.new(self._device_key(), f"{username}|{nonce}".encode(), hashlib.sha256).hexdigest()[:40]

    def new_device_cookie(self, user: User) -> str:
        """A value for the device cookie: proof that this browser logged in to `user` before."""
        nonce = secrets.token_urlsafe(12)
        return f"{nonce}.{self._device_mac(user.username, nonce)}"

    def device_id(self, username: str, cookie: str | None) -> str | None:
        """The device's id when `cookie` is a device cookie of `username`, else None."""
        if not cookie or len(cookie) > 100 or "." not in cookie:
            return None
        nonce, mac = cookie.split(".", 1)
        name = (username or "").strip().lower()
        return nonce if hmac.compare_digest(mac, self._device_mac(name, nonce)) else None


def _text(value: Any, what: str, limit: int) -> str:
    value = "" if value is None else str(value).strip()
    if len(value) > limit or any(ord(c) < 32 for c in value):
        raise AccountError(f"{what}: at most {limit} printable characters")
    return value


class RateLimiter:
    """Failed logins per key (an account name, an address): `limit` failures within `window_s`
    lock the key for lock_s, doubling with each further lock (capped at `max_lock_s`); a
    success clears the key. In memory: a restart forgets, which is fine for a lab appliance."""

    def __init__(self, limit: int = 5, window_s: float = 60.0, lock_s: float = 60.0, max_lock_s: float = 900.0) -> None:
        self.limit, self.window_s, self.lock_s, self.max_lock_s = limit, window_s, lock_s, max_lock_s
        self._fails: dict[str, list[float]] = {}
        self._locked: dict[str, float] = {}
        self._strikes: dict[str, int] = {}

    def retry_after(self, key: str) -> float:
        """Seconds until `key` may try again; 0 when it may now."""
        until = self._locked.get(key, 0.0)
        return max(0.0, until - time.monotonic())

    def failed(self, key: str) -> None:
        now = time.monotonic()
        fails = [t for t in self._fails.get(key, []) if now - t < self.window_s]
        fails.append(now)
        if len(fails) >= self.limit:
            strikes = self._strikes.get(key, 0)
            self._locked[key] = now + min(self.max_lock_s, self.lock_s * 2**strikes)
            self._strikes[key] = strikes + 1
            fails = []
        self._fails[key] = fails
        if len(self._fails) > 10_000:  # a flood of made-up names must not grow memory forever
            self._prune(now)

    def succeeded(self, key: str) -> None:
        for d in (self._fails, self._locked, self._strikes):
            d.pop(key, None)

    def _prune(self, now: float) -> None:
        for key in [k for k, v in self._fails.items() if not v or now - v[-1] > self.window_s]:
            self._fails.pop(key, None)
        for key in [k for k, v in self._locked.items() if v < now - self.max_lock_s]:
            self._locked.pop(key, None)
            self._strikes.pop(key, None)


class LoginGuard:
    """Who may try a password now; failures are counted so that guessing stays bounded while an
    anonymous client cannot keep an account (the educator's included) locked for others.

    - per (account, client): ``per_client`` failures lock the account *for that client only*
      (a client is its address, or a device cookie of the account: below). An attacker locks
      themselves out, never the owner at another address.
    - per address: ``per_address`` failures on any accounts lock the address (spraying).
    - per account, all clients together: ``per_account`` failures (a guesser with many
      addresses) lock the account for clients it does not know: addresses it logged in from
      since the appliance started and browsers with its device cookie stay welcome.
    - device cookie: set at each login (HttpOnly), proves the browser logged in to the account
      before (it carries no session). With it only its own per-(account, device) count
      applies, so an attacker behind the same NAT address as the educator cannot lock the
      educator out either; guessing is still bounded (the cookie is only had by knowing the
      password).

    Each lock lasts ``lock_s``, doubling with each further lock of the same key up to
    ``max_lock_s``; a success clears that client's count. In memory, like RateLimiter.
    """

    KNOWN_PER_ACCOUNT = 32  # addresses remembered per account (most recent successes)

    def __init__(
        self,
        per_client: int = 5,
        per_address: int = 20,
        per_account: int = 50,
        window_s: float = 60.0,
        lock_s: float = 60.0,
        max_lock_s: float = 900.0,
    ) -> None:
        self.client = RateLimiter(per_client, window_s, lock_s, max_lock_s)
        self.address = RateLimiter(per_address, window_s, lock_s, max_lock_s)
        self.account = RateLimiter(per_account, window_s, lock_s, max_lock_s)
        self._known: dict[str, dict[str, None]] = {}  # account -> addresses (insertion-ordered)

    @staticmethod
    def _client(account: str, address: str, device: str | None) -> str:
        return f"{account}\0" + (f"device:{device}" if device else f"addr:{address}")

    def _known_address(self, account: str, address: str) -> bool:
        return address in self._known.get(account, {})

    def retry_after(self, account: str, address: str, device: str | None = None) -> float:
        """Seconds until this client may try this account again; 0 when it may now."""
        wait = self.client.retry_after(self._client(account, address, device))
        if device is None:
            wait = max(wait, self.address.retry_after(address))
            if not self._known_address(account, address):
                wait = max(wait, self.account.retry_after(account))
        return wait

    def failed(self, account: str, address: str, device: str | None = None) -> None:
        self.client.failed(self._client(account, address, device))
        if device is None:
            self.address.failed(address)
        self.account.failed(account)

    def succeeded(self, account: str, address: str, device: str | None = None) -> None:
        self.client.succeeded(self._client(account, address, device))
        known = self._known.setdefault(account, {})
        known.pop(address, None)
        known[address] = None
        while len(known) > self.KNOWN_PER_ACCOUNT:
            known.pop(next(iter(known)))
        if len(self._known) > 10_000:  # made-up account names never succeed: only real ones land here
            self._known.pop(next(iter(self._known)))
