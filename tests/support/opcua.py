"""The OPC UA tests share: an asyncua session on the cell (nodes by path, methods with Variants), a job's start."""

from __future__ import annotations

import asyncio
import json

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

from tests.support.wait import eventually

S, D, I32, U32, B = (ua.VariantType.String, ua.VariantType.Double, ua.VariantType.Int32, ua.VariantType.UInt32,
                     ua.VariantType.Boolean)


SMALL = json.dumps({"rows": 4, "cols": 4, "n_verify": 8, "passes": 1})


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


class Session:
    """An asyncua client session on the cell: nodes by path under Objects/Cell, methods called with Variants."""

    def __init__(self, cell, user: str | None = None, password: str | None = None, secure=None, user_cert=None):
        self.client = Client(cell.url, timeout=10)
        if user is not None:
            self.client.set_user(user)
            self.client.set_password(password)
        self.secure, self.user_cert = secure, user_cert

    async def __aenter__(self):
        if self.secure is not None:
            identity, mode = self.secure
            self.client.application_uri = identity.uri  # the certificate names it; asyncua checks before use
            await self.client.set_security(SecurityPolicyBasic256Sha256, str(identity.pem), str(identity.key),
                                           mode=mode)
        if self.user_cert is not None:  # an X.509 user identity token, signed with the user's key
            await self.client.load_client_certificate(str(self.user_cert.pem))
            await self.client.load_private_key(self.user_cert.key)
        await self.client.connect()
        self.ns = await self.client.get_namespace_index("urn:cellctl")
        return self

    async def __aexit__(self, *exc):
        await self.client.disconnect()

    async def node(self, path: str):
        parts = [p for p in path.split("/") if p]
        return await self.client.nodes.objects.get_child([f"{self.ns}:Cell", *(f"{self.ns}:{p}" for p in parts)])

    async def read(self, path: str):
        return await (await self.node(path)).read_value()

    async def call(self, path: str, *args: ua.Variant):
        parent, _, name = path.rpartition("/")
        return await (await self.node(parent)).call_method(f"{self.ns}:{name}", *args)


def start_args(routine="virtual-grid", params=SMALL, seed=3):
    return ua.Variant(routine, S), ua.Variant(params, S), ua.Variant(seed, I32)


def jobs(cell) -> list[dict]:
    with cell.daemon.client() as http:
        return http.get("/jobs", params={"limit": 1000}).json()["jobs"]


def wait_idle(cell, timeout=120.0):
    with cell.daemon.client() as http:
        eventually(lambda: http.get("/cell").json()["job"] is None, timeout=timeout, every=0.2, what="the cell idle")
