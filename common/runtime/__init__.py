"""What every process on a cell runs on: the bus (Zenoh from asyncio), the service lifecycle and its
configuration, data time, files written atomically, the error tree, what a message must fit to be acted
on, and the deployed cell's accounts and access control."""
