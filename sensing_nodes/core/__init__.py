"""Pure numpy/scipy algorithms; never imports rclpy or message types."""
