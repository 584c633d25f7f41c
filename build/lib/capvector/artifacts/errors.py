"""Errors of the store and the catalogue, one class per fault a user must be able to tell apart."""


class ArtifactError(Exception):
    """Base class, so callers (CLI, tasks) can catch every store/catalogue fault at once."""


class MalformedId(ArtifactError, ValueError):
    """An id that is not 6 to 64 lowercase hex characters."""


class ArtifactNotFound(ArtifactError, LookupError):
    """No committed artifact (one with a sidecar) has this id or prefix."""


class AmbiguousId(ArtifactError, LookupError):
    """A prefix that matches several artifacts; the message lists them."""

    def __init__(self, prefix: str, candidates: list[str]):
        self.prefix, self.candidates = prefix, candidates
        super().__init__(f"id prefix {prefix!r} matches {len(candidates)} artifacts: {', '.join(candidates)}")


class CorruptArtifact(ArtifactError):
    """Stored content no longer hashes to what was recorded; the artifact is never served."""

    def __init__(self, artifact_id: str, detail: str):
        self.artifact_id = artifact_id
        super().__init__(f"artifact {artifact_id} is corrupt: {detail}")


class UnknownParent(ArtifactError, LookupError):
    """A registration names a parent that is not in the store; nothing is written."""

    def __init__(self, parent_id: str):
        self.parent_id = parent_id
        super().__init__(f"parent artifact {parent_id} does not exist in the store; nothing was written")


class PathEscape(ArtifactError, ValueError):
    """A relative path that would leave the store root or the artifact's directory."""


class SchemaTooNew(ArtifactError):
    """The catalogue was written by newer code; opening it with older code could lose data."""

    def __init__(self, found: int, known: int, path: str):
        self.found, self.known = found, known
        super().__init__(
            f"catalogue {path} has schema version {found}, this code knows up to version {known}; "
            "upgrade capvector, or delete the file and run `capvector catalogue rebuild` to recreate it "
            "from the store"
        )


class CatalogueBusy(ArtifactError):
    """Another process held the DuckDB lock for longer than the bounded wait.

    Reads report it; registrations do not (the sidecar is the commit point: the row is indexed on a
    later write, open or `capvector catalogue sync`)."""


class ReadOnlyViolation(ArtifactError, ValueError):
    """A statement given to the read-only SQL entry point that is not a single read."""


class MixedFingerprints(ArtifactError):
    """Scores under different evaluation protocols were requested together; they are not comparable."""

    def __init__(self, fingerprints: list[str]):
        self.fingerprints = fingerprints
        super().__init__(
            "scores come from different evaluation protocols (fingerprints "
            f"{', '.join(fingerprints)}); pass fingerprint= to choose one"
        )
