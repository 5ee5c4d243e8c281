"""The ``alerts:`` section of a site file: rules and webhooks (pydantic, every key checked).

Example::

    alerts:
      rules:
        - {name: crowd, kind: occupancy, zone: market, above: 10, for_s: 30}
        - {name: loitering, kind: dwell, zone: market, above_s: 300}
        - {name: rush, kind: line_count, line: gate, above: 50, per_s: 60}
        - {name: camera down, kind: camera_offline, for_s: 30}      # camera: NAME, or any
        - {name: behind, kind: matcher_lag, above_s: 10, for_s: 5}
      webhooks:
        - {name: ops, url: "https://ops.example/cblrs", secret_env: CBLRS_OPS_SECRET}

A webhook's secret signs its requests; it is read from a file (``secret_file``, readable by
its owner only) or an environment variable (``secret_env``) and never written in the site
file, where it would sit in clear beside every camera's geometry.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cblrs.errors import CblrsError


class AlertsError(CblrsError):
    """The ``alerts:`` section is invalid, or a webhook's secret cannot be read."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Name = Annotated[str, Field(min_length=1, max_length=100)]


class OccupancyRule(_Strict):
    """More than ``above`` confirmed tracks in ``zone`` for at least ``for_s`` seconds."""

    name: Name
    kind: Literal["occupancy"]
    zone: Name
    above: int = Field(ge=0)
    for_s: float = Field(default=0.0, ge=0)


class DwellRule(_Strict):
    """A visit to ``zone`` that has lasted more than ``above_s`` seconds (one episode per
    zone: from the first such visit until none is left)."""

    name: Name
    kind: Literal["dwell"]
    zone: Name
    above_s: float = Field(gt=0)


class LineCountRule(_Strict):
    """More than ``above`` crossings of ``line`` (in ``direction``) in the last ``per_s``
    seconds."""

    name: Name
    kind: Literal["line_count"]
    line: Name
    above: int = Field(ge=0)
    per_s: float = Field(gt=0)
    direction: Literal["positive", "negative", "both"] = "both"


class CameraOfflineRule(_Strict):
    """A camera (``camera``, or each camera) offline for at least ``for_s`` seconds."""

    name: Name
    kind: Literal["camera_offline"]
    camera: Name | None = None
    for_s: float = Field(default=30.0, ge=0)


class MatcherLagRule(_Strict):
    """The matcher's tracks lagging capture time by more than ``above_s`` seconds for at
    least ``for_s`` seconds."""

    name: Name
    kind: Literal["matcher_lag"]
    above_s: float = Field(gt=0)
    for_s: float = Field(default=0.0, ge=0)


Rule = Annotated[
    OccupancyRule | DwellRule | LineCountRule | CameraOfflineRule | MatcherLagRule,
    Field(discriminator="kind"),
]


class WebhookModel(_Strict):
    """Where alerts are POSTed, and how hard to try.

    Attributes:
        name: names the webhook in logs and counters.
        url: ``http://`` or ``https://`` address.
        secret_file: a file holding the HMAC secret (mode 0600: only its owner reads it).
        secret_env: or the environment variable holding it.
        timeout_s: one attempt's time-out.
        retries: attempts after the first, with back-off ``backoff_s * 2**n`` (capped at
            ``max_backoff_s``).
    """

    name: Name
    url: str
    secret_file: str | None = None
    secret_env: str | None = None
    timeout_s: float = Field(default=5.0, gt=0, le=60)
    retries: int = Field(default=5, ge=0, le=20)
    backoff_s: float = Field(default=1.0, gt=0)
    max_backoff_s: float = Field(default=60.0, gt=0)

    @model_validator(mode="before")
    @classmethod
    def _no_clear_secret(cls, data: Any) -> Any:
        if isinstance(data, dict) and ("secret" in data or "token" in data):
            raise ValueError(
                "a webhook's secret never goes in the site file in clear: give secret_file "
                "(a file only its owner can read) or secret_env (an environment variable)"
            )
        return data

    @model_validator(mode="after")
    def _checked(self) -> WebhookModel:
        parts = urlsplit(self.url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"url must be an http:// or https:// address, got {self.url!r}")
        if parts.username or parts.password:
            raise ValueError("url must not carry a user or password (they would be in clear)")
        if (self.secret_file is None) == (self.secret_env is None):
            raise ValueError("give exactly one of secret_file or secret_env (the HMAC secret)")
        return self


class AlertsModel(_Strict):
    """The whole ``alerts:`` section."""

    rules: list[Rule] = Field(default_factory=list)
    webhooks: list[WebhookModel] = Field(default_factory=list)

    @model_validator(mode="after")
    def _unique(self) -> AlertsModel:
        for what, names in (("rule", [rule.name for rule in self.rules]),
                            ("webhook", [hook.name for hook in self.webhooks])):
            seen: set[str] = set()
            for name in names:
                if name in seen:
                    raise ValueError(f"two {what}s are named {name!r}; names must be unique")
                seen.add(name)
        return self


def load_alerts(
    data: Any,
    source: str = "site",
    zones: tuple[str, ...] | list[str] | None = None,
    lines: tuple[str, ...] | list[str] | None = None,
    cameras: tuple[str, ...] | list[str] | None = None,
) -> AlertsModel:
    """Validate an ``alerts:`` section; the places and cameras it names must exist.

    Args:
        data: the section as read from YAML/JSON (``None``: no alerts).
        source: the file, for messages.
        zones, lines, cameras: the site's names (None: not checked).

    Raises:
        AlertsError: one sentence naming the file and the key.
    """
    if data is None:
        return AlertsModel()
    try:
        model = AlertsModel.model_validate(data)
    except ValidationError as error:
        raise AlertsError(_sentence(error.errors(include_url=False)[0], source, data)) from None
    known = {"zone": zones, "line": lines, "camera": cameras}
    for index, rule in enumerate(model.rules):
        for key, names in known.items():
            value = getattr(rule, key, None)
            if value is not None and names is not None and value not in names:
                raise AlertsError(
                    f"{source}: alerts.rules[{index}] ({rule.name}): the site has no {key} "
                    f"{value!r} ({', '.join(names) or 'none'})."
                )
    return model


RULE_MODELS: dict[str, type[BaseModel]] = {
    "occupancy": OccupancyRule, "dwell": DwellRule, "line_count": LineCountRule,
    "camera_offline": CameraOfflineRule, "matcher_lag": MatcherLagRule,
}
"""Each rule ``kind`` and its model (the keys a rule of that kind takes)."""


def _sentence(item: Any, source: str, data: Any) -> str:
    """A pydantic error of the section as the site file's other sentences read:
    ``site.yaml: alerts.rules[0] (crowd).for_s: ...`` (the rule's name, no union tag)."""
    loc = list(item["loc"])
    kind = item["type"]
    if len(loc) >= 3 and loc[0] == "rules" and loc[2] in RULE_MODELS:
        loc.pop(2)  # pydantic names the union's member; the file has no such key
    entry = None
    if len(loc) >= 2 and isinstance(data, dict) and isinstance(data.get(loc[0]), list):
        entries = data[loc[0]]
        if isinstance(loc[1], int) and loc[1] < len(entries) and isinstance(entries[loc[1]], dict):
            entry = entries[loc[1]]
    where = "alerts"
    for index, part in enumerate(loc):
        where += f"[{part}]" if isinstance(part, int) else f".{part}"
        if index == 1 and entry is not None and entry.get("name"):
            where += f" ({entry['name']})"
    message = str(item["msg"]).removeprefix("Value error, ")
    kinds = ", ".join(RULE_MODELS)
    if kind == "union_tag_invalid":
        message = f"kind must be one of {kinds}; got {entry.get('kind')!r}" if entry else message
    elif kind == "union_tag_not_found":
        message = f"a rule needs kind: one of {kinds}"
    elif kind == "missing":
        message = "required key is missing"
    elif kind == "extra_forbidden":
        model: type[BaseModel] = AlertsModel
        if len(loc) >= 2 and loc[0] == "webhooks":
            model = WebhookModel
        elif len(loc) >= 2 and loc[0] == "rules" and entry is not None:
            model = RULE_MODELS.get(str(entry.get("kind")), AlertsModel)
        message = f"unknown key (allowed: {', '.join(model.model_fields)})"
    return f"{source}: {where}: {message.rstrip('.')}."
