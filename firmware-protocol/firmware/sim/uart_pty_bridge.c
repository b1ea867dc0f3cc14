/*
 * Runs a firmware ELF in simavr (ATmega328P, 16 MHz) and bridges UART0 to a pseudo-terminal.
 * Prints `PTY <path>` on a line of stdout (simavr may print other lines first), then runs until killed or
 * until stdin is closed (so it never outlives the process that started it).
 *
 * usage: uart_pty_bridge FIRMWARE.elf
 */
#define _DEFAULT_SOURCE
#define _XOPEN_SOURCE 600
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>

static int master_fd = -1;
static int xon = 1;
static unsigned char queue[4096];
static size_t q_head, q_len;

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    (void)param;
    unsigned char b = (unsigned char)value;
    if (write(master_fd, &b, 1) < 0 && errno != EAGAIN) {
        /* Nobody on the other end yet: the byte is lost, as on a real line. */
    }
}
static void xon_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)value; (void)param;
    xon = 1;
}
static void xoff_hook(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq; (void)value; (void)param;
    xon = 0;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s FIRMWARE.elf\n", argv[0]);
        return 2;
    }
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(argv[1], &fw) != 0) {
        fprintf(stderr, "cannot read %s\n", argv[1]);
        return 1;
    }
    avr_t *avr = avr_make_mcu_by_name("atmega328p");
    if (!avr) {
        fprintf(stderr, "simavr has no atmega328p core\n");
        return 1;
    }
    avr_init(avr);
    avr->frequency = 16000000;
    avr_load_firmware(avr, &fw);

    master_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (master_fd < 0 || grantpt(master_fd) || unlockpt(master_fd)) {
        perror("pseudo-terminal");
        return 1;
    }
    const char *slave = ptsname(master_fd);
    /* Keep the slave open in raw mode so that no line discipline echoes or edits bytes, and so
     * that the master does not hang up while the host has the port closed. */
    int slave_fd = open(slave, O_RDWR | O_NOCTTY);
    struct termios t;
    if (slave_fd < 0 || tcgetattr(slave_fd, &t)) {
        perror("slave");
        return 1;
    }
    cfmakeraw(&t);
    tcsetattr(slave_fd, TCSANOW, &t);
    fcntl(master_fd, F_SETFL, fcntl(master_fd, F_GETFL) | O_NONBLOCK);

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~AVR_UART_FLAG_STDIO;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), uart_out_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), xon_hook, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), xoff_hook, NULL);
    avr_irq_t *in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);

    printf("PTY %s\n", slave);
    fflush(stdout);

    for (;;) {
        for (int i = 0; i < 2000; i++) {
            int state = avr_run(avr);
            if (state == cpu_Done || state == cpu_Crashed) {
                fprintf(stderr, "firmware stopped (state %d)\n", state);
                return 1;
            }
        }
        struct pollfd p[2] = {{.fd = master_fd, .events = POLLIN}, {.fd = 0, .events = POLLIN}};
        if (poll(p, 2, 0) > 0) {
            if (p[1].revents & (POLLIN | POLLHUP)) {
                char c;
                if (read(0, &c, 1) <= 0) return 0; /* parent went away */
            }
            if ((p[0].revents & POLLIN) && q_len < sizeof queue / 2) {
                unsigned char buf[256];
                ssize_t n = read(master_fd, buf, sizeof buf);
                for (ssize_t k = 0; k < n; k++) queue[(q_head + q_len++) % sizeof queue] = buf[k];
            }
        }
        while (xon && q_len) {
            avr_raise_irq(in, queue[q_head]);
            q_head = (q_head + 1) % sizeof queue;
            q_len--;
        }
    }
}
