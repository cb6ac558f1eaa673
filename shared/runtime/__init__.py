"""Layer 4: what every service process shares: settings, the service entry point, logging, camera sources."""
