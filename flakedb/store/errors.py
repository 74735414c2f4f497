"""The store's exceptions, apart from the store itself: the command line's error handling names them
without importing Zarr (``flakedb.store.versions`` re-exports both)."""


class StoreError(RuntimeError):
    """The store cannot give what was asked (no version, incomplete version, unknown species).

    A checksum failure is a store error, so ``except StoreError`` catches both:

    >>> issubclass(StoreIntegrityError, StoreError), issubclass(StoreError, RuntimeError)
    (True, True)
    """


class StoreIntegrityError(StoreError):
    """The stored bytes do not match their recorded checksums, or the metadata breaks the schema."""
