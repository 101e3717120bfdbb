"""Sony VISCA over RS-232: sans-IO codec, asyncio link, typed camera API."""
