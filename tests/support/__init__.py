"""What the tests share: the cell a test runs (on the in-memory bus or on Zenoh), the recordings, the
example task and its sets, and the helpers of the tests of one service used by another's. A test module
imports from here, never from another test module."""
