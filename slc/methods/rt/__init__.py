"""rtN: N random light samples per pixel with shadow rays."""
