"""Object key layout and validation.

Keys are relative, `/`-separated paths. Every key and prefix is checked here so that a key can never
climb out of the local storage root or name an object of another tenant: no `..` or `.` component,
no leading `/`, no backslash, no empty component, no control character.

Layout:
    tenants/{tenant}/projects/{project}/images/{set}/{filename}
    tenants/{tenant}/projects/{project}/jobs/{job}/{stage}/{name}
"""

from __future__ import annotations

MAX_KEY_BYTES = 1024  # the S3 limit


class InvalidKeyError(ValueError):
    """A key or prefix that is not a safe relative path."""


def _check_parts(text: str, what: str) -> None:
    if "\\" in text:
        raise InvalidKeyError(f"{what} {text!r}: backslashes are not allowed")
    if text.startswith("/"):
        raise InvalidKeyError(f"{what} {text!r}: must be relative (no leading '/')")
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        raise InvalidKeyError(f"{what} {text!r}: control characters are not allowed")
    if len(text.encode()) > MAX_KEY_BYTES:
        raise InvalidKeyError(f"{what} is longer than {MAX_KEY_BYTES} bytes")
    for part in text.split("/"):
        if part in ("", ".", ".."):
            raise InvalidKeyError(f"{what} {text!r}: empty, '.' or '..' path component")


def validate_key(key: str) -> str:
    """Return key if it is a safe object key, raise InvalidKeyError otherwise."""
    if not isinstance(key, str) or not key:
        raise InvalidKeyError(f"key {key!r}: must be a non-empty string")
    _check_parts(key, "key")
    return key


def validate_prefix(prefix: str) -> str:
    """Return prefix if safe; a prefix may end with '/' (a folder) or be a partial name."""
    if not isinstance(prefix, str):
        raise InvalidKeyError(f"prefix {prefix!r}: must be a string")
    if prefix:
        body = prefix[:-1] if prefix.endswith("/") else prefix
        if not body:
            raise InvalidKeyError("prefix '/': must be relative")
        _check_parts(body, "prefix")
    return prefix


def component(value: object, what: str = "component") -> str:
    """One path component (an id, a set, a stage, a file name): no '/' and safe."""
    text = str(value)
    if "/" in text:
        raise InvalidKeyError(f"{what} {text!r}: must not contain '/'")
    if not text:
        raise InvalidKeyError(f"{what}: must not be empty")
    _check_parts(text, what)
    return text


def tenant_prefix(tenant_id: object) -> str:
    """`tenants/{tenant}/`"""
    return f"tenants/{component(tenant_id, 'tenant')}/"


def project_prefix(tenant_id: object, project_id: object) -> str:
    """`tenants/{tenant}/projects/{project}/`"""
    return f"{tenant_prefix(tenant_id)}projects/{component(project_id, 'project')}/"


def cameras_key(tenant_id: object, project_id: object) -> str:
    """`tenants/{tenant}/projects/{project}/cameras.json`: the project's intrinsics per image set."""
    return f"{project_prefix(tenant_id, project_id)}cameras.json"


def image_key(tenant_id: object, project_id: object, image_set: str, filename: str) -> str:
    """`tenants/{tenant}/projects/{project}/images/{set}/{filename}`"""
    return (
        f"{project_prefix(tenant_id, project_id)}images/"
        f"{component(image_set, 'image set')}/{component(filename, 'file name')}"
    )


def split_image_name(name: str) -> tuple[str, str]:
    """`aerial/A0001.jpg` -> (`aerial`, `A0001.jpg`) (docs/formats.md); raises InvalidKeyError."""
    image_set, sep, filename = str(name).partition("/")
    if not sep:
        raise InvalidKeyError(f"image name {name!r}: expected SET/FILE, e.g. aerial/A0001.jpg")
    return component(image_set, "image set"), component(filename, "file name")


def image_key_for_name(tenant_id: object, project_id: object, name: str) -> str:
    """The key of an image given its name (`aerial/A0001.jpg`)."""
    return image_key(tenant_id, project_id, *split_image_name(name))


def job_prefix(tenant_id: object, project_id: object, job_id: object) -> str:
    """`tenants/{tenant}/projects/{project}/jobs/{job}/`"""
    return f"{project_prefix(tenant_id, project_id)}jobs/{component(job_id, 'job')}/"


def job_key(tenant_id: object, project_id: object, job_id: object, stage: str, name: str) -> str:
    """`.../jobs/{job}/{stage}/{name}`; name may hold '/' (a relative path inside the stage folder)."""
    return validate_key(f"{job_prefix(tenant_id, project_id, job_id)}{component(stage, 'stage')}/{name}")
