"""A base for drivers that tests stand in for a device: the context-manager part of the contract."""


class StandInDriver:
    """Nothing to open or close; subclasses set ``rate``, ``channels`` and give ``read`` and ``stats``."""

    def open(self):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass
